"""``trainer.cli.train_report``: the KL warnings and the summary morph-train reads from a run's progress.csv as
the trainer appends to it (real files, written as ``algo.run_log`` writes them: a header, then a row per
update, appended and flushed; a resumed run's file replaced by a copy cut at its checkpoint)."""

import csv
import os

import pytest

from morph_core.algo.run_dir import RunDir
from trainer.cli.train_report import MAX_WARNINGS, ProgressFollower

COLUMNS = ["global_step", "iteration", "episodes", "return_mean", "approx_kl"]


def _write(path, rows, header=True, mode="a", end="\n"):
    with path.open(mode, newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        if header:
            w.writerow(COLUMNS)
        for r in rows:
            f.write(",".join(str(v) for v in r) + end)


def test_high_kl_updates_are_warned_about_as_they_are_logged(tmp_path, capsys):
    csv_path = RunDir(tmp_path).progress
    follower = ProgressFollower(tmp_path, kl_limit=0.1)
    follower.poll()  # no file yet: nothing
    _write(csv_path, [(100, 1, 2, 10.0, 0.01), (200, 2, 0, "", 0.5)], mode="w")
    follower.poll()
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "morph-train: warning: update 2 (step 200): approximate KL 0.5 > 0.1 (10x kl_target): the policy moved far "
        "from the one that acted; a lower --learning-rate keeps it closer"
    ]
    _write(csv_path, [(300, 3, 3, 20.0, 0.2)], header=False, end="")  # a row being written: read once complete
    follower.poll()
    assert capsys.readouterr().err == "" and len(follower.rows) == 2
    with csv_path.open("a") as f:
        f.write("\n")
    follower.poll()
    assert "update 3 (step 300): approximate KL 0.2 > 0.1" in capsys.readouterr().err
    _write(csv_path, [(400, 4, 0, "", 7.0), (500, 5, 0, "", 9.0), (600, 6, 0, "", 0.05)], header=False)
    follower.poll()
    err = capsys.readouterr().err.splitlines()
    assert len(err) == MAX_WARNINGS - 2 == 1 and err[0].endswith("(further ones are counted, not said)")
    assert len(follower.high_kl) == 4
    head, where = follower.summary(tmp_path)
    assert head == (
        "morph-train: done: step 600 (update 6); training return 16.0 (mean of its last 5 episodes); last update's "
        "approximate KL 0.05; 4 of 6 updates above KL 0.1 (max 9)"
    )  # (2 x 10 + 3 x 20) / 5
    assert where == f"morph-train: files in {tmp_path}: config.json, progress.csv"


def test_a_resumed_run_s_earlier_rows_are_not_warned_about_again(tmp_path, capsys):
    csv_path = RunDir(tmp_path).progress
    # A run killed at step 300, its last checkpoint at 200: the row at 300 is logged again after the resume.
    _write(csv_path, [(100, 1, 1, 5.0, 0.9), (200, 2, 1, 6.0, 0.9), (300, 3, 1, 7.0, 0.9)], mode="w")
    follower = ProgressFollower(tmp_path, kl_limit=0.1, start_step=200)
    follower.poll()  # the file before the resumed trainer cut it: not read (its row at 300 is not this session's)
    assert follower.rows == [] and capsys.readouterr().err == ""
    _write(tmp_path / "new.csv", [(100, 1, 1, 5.0, 0.9), (200, 2, 1, 6.0, 0.9)], mode="w")
    os.replace(tmp_path / "new.csv", csv_path)  # the file cut at the checkpoint, put in place
    follower.poll()
    _write(csv_path, [(300, 3, 1, 8.0, 0.01), (400, 4, 1, 9.0, 0.3)], header=False)
    follower.poll()
    assert capsys.readouterr().err.splitlines() == [
        "morph-train: warning: update 4 (step 400): approximate KL 0.3 > 0.1 (10x kl_target): the policy moved far "
        "from the one that acted; a lower --learning-rate keeps it closer"
    ]
    assert [r["global_step"] for r in follower.session] == ["300", "400"]
    assert [r["global_step"] for r in follower.high_kl] == ["400"]
    assert follower.training_return() == (pytest.approx((5.0 + 6.0 + 8.0 + 9.0) / 4), 4)


def test_the_follower_warns_while_the_run_goes_on(tmp_path, capsys):
    csv_path = RunDir(tmp_path).progress
    with ProgressFollower(tmp_path, kl_limit=0.1) as follower:
        _write(csv_path, [], mode="w")
        follower.on_row({}, False)  # the header read alone first
        _write(csv_path, [(64, 1, 0, "", 3.0)], header=False)
        follower.on_row({"global_step": 64}, False)  # the trainer's row hook, as the row is written
        assert follower.high_kl, "not read while the run was going on"
    assert "update 1 (step 64): approximate KL 3 > 0.1" in capsys.readouterr().err
