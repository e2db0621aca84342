"""trainer.live.compare on hand-made progress rows: returns read at each run's last update before a mark,
smoothed as trainer.reports.summary does, and the table and figure written from them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from trainer.live.compare import plot, return_at, stability_table, table
from trainer.reports.runs import RunReport


def run(name: str, steps: list[int], returns: list[float]) -> RunReport:
    rows = [{"global_step": str(s), "return_mean": str(r)} for s, r in zip(steps, returns, strict=True)]
    return RunReport(Path(name), {"clip_mode": "compensated"}, rows)


def test_return_at_takes_the_last_update_before_each_mark_smoothed_over_five():
    r = run("live-s1", [7000, 14100, 20900, 28000, 35000, 42000], [0, 10, 20, 30, 40, 50])
    got = return_at(r, np.array([5000, 7000, 20000, 42000, 50000]))
    assert np.isnan(got[0])  # before any update
    assert got[1] == 0.0 and got[2] == 5.0  # (0 + 10) / 2: the update at 14,100
    assert got[3] == np.mean([10, 20, 30, 40, 50])  # the trailing five
    assert np.isnan(got[4])  # past the run's end


def test_table_rows_and_means(tmp_path):
    groups = {
        "live over DDS": [run("live-s1", [100_000, 200_000], [10, 30]), run("live-s2", [100_000, 200_000], [20, 50])],
        "simulator": [run("simulator-s1", [100_000, 200_000], [40, 60])],
    }
    text = table(groups, [100_000, 200_000])
    lines = text.splitlines()
    assert lines[0].startswith("| source | run | at 100k | at 200k | last 10 updates |")
    assert "| live over DDS | live-s1 | 10.0 | 20.0 | 20.0 | 200000 |" in lines
    assert "| live over DDS | mean of 2 | **15.0** | **27.5** | **27.5** | |" in lines
    assert "| simulator | simulator-s1 | 40.0 | 50.0 | 50.0 | 200000 |" in lines
    png = plot(groups, tmp_path / "figs" / "live")
    assert png.suffix == ".png" and png.stat().st_size > 1000


def test_stability_table_finds_the_first_diverged_update_and_the_reward_rate():
    def rows(kls, rates=None):
        out = [{"global_step": str(7000 * (i + 1)), "return_mean": "0", "approx_kl": str(k)} for i, k in enumerate(kls)]
        for r, rate in zip(out, rates or [], strict=False):
            r["reward_rate"] = str(rate)
        return out

    groups = {
        "live": [RunReport(Path("diverged"), {}, rows([0.1, 0.3, 2.5, 11.6, 0.4], [0.0, 0.01, 0.02, 0.03, 0.04]))],
        "simulator": [RunReport(Path("steady"), {}, rows([0.05, 0.2, 0.9]))],
    }
    lines = stability_table(groups, last=2).splitlines()
    assert "| live | diverged | 5 | 11.6 | 21000 | 35.0 |" in lines
    assert "| simulator | steady | 3 | 0.9 | never | - |" in lines
