"""ROS 2 node running the morphology-agnostic GNN policy on JointState messages."""

from pathlib import Path

FASTDDS_PROFILE = Path(__file__).resolve().parent / "fastdds_profile.xml"
"""The nodes' Fast DDS profile (for ``FASTRTPS_DEFAULT_PROFILES_FILE``): quick discovery for nodes started
together, and UDP only (docs/design.md, "Topics, QoS")."""
FASTDDS_PROFILE_LOOPBACK_ONLY = Path(__file__).resolve().parent / "fastdds_profile_loopback_only.xml"
"""The same, with DDS kept to the loopback interface (an allow-list): for a robot whose nodes all run on its own
computer, nothing on any network reaches them (docs/robustness.md, "Who can change the policy")."""
