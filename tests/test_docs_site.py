"""The documentation site builds with ``mkdocs build --strict``: a broken link or anchor, a page missing
from the navigation (or a navigation entry without its page) and a docstring the API pages cannot render
all fail here. The same command a reader runs (``.venv/bin/mkdocs build --strict``), into a temporary
directory; the API pages read the packages' sources statically, so nothing is imported."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

API_PAGES = {
    "env": "morph_core.env.bodies.parse_bodies",
    "policy": "morph_core.policy.actor_critic.GraphActorCritic",
    "algo": "morph_core.algo.trust_region.RULES",
    "theory": "morph_core.theory.clip_analysis",
    "msgs": "morph_core.msgs.records.JointStateRecord",
    "protocol": "morph_core.protocol.transitions.TransitionAssembler",
    "util": "morph_core.util.atomic.atomic_writer",
    "trainer": "trainer.bags.io.BagReader",
}
"""API page -> an object whose heading it must hold (the page rendered its package's modules)"""


@pytest.mark.slow
def test_the_docs_site_builds_strict(tmp_path):
    site = tmp_path / "site"
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}  # Material's notice about MkDocs 2.0: not ours to fix
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(ROOT / "mkdocs.yml")]
        + ["--site-dir", str(site)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, f"mkdocs build --strict failed:\n{result.stdout}\n{result.stderr}"
    assert (site / "index.html").is_file()
    for page, identifier in API_PAGES.items():
        html = (site / "api" / page / "index.html").read_text(encoding="utf-8")
        assert f'id="{identifier}"' in html, f"api/{page}.md did not render {identifier}"
