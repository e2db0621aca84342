"""ROS 2 node running the morphology-agnostic GNN policy on JointState messages."""

from pathlib import Path

FASTDDS_PROFILE = Path(__file__).resolve().parent / "fastdds_profile.xml"
"""The nodes' Fast DDS profile (for ``FASTRTPS_DEFAULT_PROFILES_FILE``): quick discovery for nodes started
together, and UDP only (docs/design.md, "Topics, QoS")."""
