"""The run log: a row with a column it does not know is refused, not silently dropped."""

import csv

import pytest

from morph_core.algo.run_dir import RunDir
from morph_core.algo.run_log import RunLog


def _rows(path):
    with path.open() as f:
        return list(csv.DictReader(f))


def test_unknown_column_is_refused_and_nothing_is_written(tmp_path):
    log = RunLog(tmp_path, ["global_step", "loss"], tensorboard=False)
    log.log({"global_step": 1, "loss": 0.5})
    with pytest.raises(ValueError, match=r"\['lost'\]"):
        log.log({"global_step": 2, "lost": 0.4})
    log.log({"global_step": 3, "loss": float("nan")})  # missing values and NaN: empty cells
    log.close()
    assert _rows(RunDir(tmp_path).progress) == [{"global_step": "1", "loss": "0.5"}, {"global_step": "3", "loss": ""}]


def test_resuming_drops_later_rows_and_refuses_a_file_with_other_columns(tmp_path):
    log = RunLog(tmp_path, ["global_step", "loss"], tensorboard=False)
    for step in (1, 2, 3):
        log.log({"global_step": step, "loss": step / 10})
    log.close()
    RunLog(tmp_path, ["global_step", "loss"], resume_step=2, tensorboard=False).close()
    assert [r["global_step"] for r in _rows(RunDir(tmp_path).progress)] == ["1", "2"]
    with pytest.raises(ValueError, match=r"columns \['loss'\]"):
        RunLog(tmp_path, ["global_step"], resume_step=2, tensorboard=False)
