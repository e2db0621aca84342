"""TensorBoard: multi-line charts per dimension and log-ratio histograms, read back from a real run's event files."""

import csv
import math
import re

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.custom_scalar import layout_pb2, metadata

from morph_core.algo.run_dir import RunDir
from morph_core.algo.run_log import HISTOGRAM_BINS
from morph_core.algo.tb_layout import custom_scalars_layout, scalar_tag
from morph_core.algo.train import TrainConfig, log_columns, train

# 1024 steps per swimmer: each finishes one 1000-step episode, so returns per chain length get logged.
SHORT = dict(
    num_envs=2, num_steps=512, minibatch_size=128, update_epochs=2, checkpoint_interval=1024,
    min_joints=2, max_joints=4, progress_bar=False, compile=False, seed=4,
)  # fmt: skip


def _events(tb_dir) -> EventAccumulator:
    acc = EventAccumulator(str(tb_dir), size_guidance={"scalars": 0, "histograms": 0, "tensors": 0})
    acc.Reload()
    return acc


def _charts(acc: EventAccumulator) -> dict[str, list[str]]:
    """chart title -> its multi-line tag regexes, from the custom-scalars layout in the event files."""
    protos = acc.Tensors(metadata.CONFIG_SUMMARY_TAG)
    assert protos, "no custom-scalars layout in the event files"
    layout = layout_pb2.Layout.FromString(protos[-1].tensor_proto.string_val[0])
    return {c.title: list(c.multiline.tag) for cat in layout.category for c in cat.chart}


def _rows(run_dir) -> list[dict]:
    with RunDir(run_dir).progress.open() as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A short real training run with TensorBoard on, interrupted once and resumed."""
    run_dir = tmp_path_factory.mktemp("tb_run") / "run"
    train(TrainConfig(total_timesteps=1024, **SHORT), run_dir)
    train(TrainConfig(total_timesteps=2048, **SHORT), run_dir, resume=True)
    return run_dir


def test_layout_charts_every_chain_length_and_each_line_is_a_logged_scalar(run):
    acc = _events(RunDir(run).tensorboard)
    charts = _charts(acc)
    dims = range(2, 5)
    assert charts["return per chain length"] == [f"^return/d{d}$" for d in dims]
    assert charts["clip fraction per action dimension"] == [f"^clip_frac/d{d}$" for d in dims]
    assert charts["clip fraction per action dimension (last epoch)"] == [f"^clip_frac_last/d{d}$" for d in dims]
    scalars = set(acc.Tags()["scalars"])
    rows = _rows(run)
    assert [int(r["global_step"]) for r in rows] == [1024, 2048]
    returns = 0
    for family, title in (("return", "return per chain length"), ("clip_frac", "clip fraction per action dimension")):
        for d, pattern in zip(dims, charts[title], strict=True):
            tag = f"{family}/d{d}"
            # TensorBoard searches with the pattern: each line must draw its own chain length and nothing else.
            assert [t for t in scalars if re.search(pattern, t)] == ([tag] if tag in scalars else [])
            logged = {e.step: e.value for e in acc.Scalars(tag)} if tag in scalars else {}
            for r in rows:
                value = r[f"{family}_d{d}"]
                if value:  # a length with no finished episode (or no sample) has no point, as in the CSV
                    assert logged[int(r["global_step"])] == pytest.approx(float(value), rel=1e-6)
                    returns += family == "return"
    assert returns >= 1, "no episode finished: the run is too short to test the return chart"


@pytest.mark.parametrize(("tag", "suffix", "epochs"), [("log_ratio", "", 2), ("log_ratio_last", "_last", 1)])
def test_each_update_logs_log_ratio_histograms_per_dimension(run, tag, suffix, epochs):
    acc = _events(RunDir(run).tensorboard)
    rows = {int(r["global_step"]): r for r in _rows(run)}
    histograms = [t for t in acc.Tags()["histograms"] if t.startswith(f"{tag}/d")]
    assert histograms
    for step, row in rows.items():
        total = 0
        for d in range(2, 5):
            events = [e for e in acc.Histograms(f"{tag}/d{d}") if e.step == step] if f"{tag}/d{d}" in histograms else []
            mean_col = row[f"logr_mean{suffix}_d{d}"]
            assert bool(events) == bool(mean_col), (step, d)  # a histogram exactly where the CSV has samples
            if not events:
                continue
            (h,) = events
            hv = h.histogram_value
            total += hv.num
            # The histogram holds exactly the samples the per-dimension columns summarise.
            mean = hv.sum / hv.num
            assert mean == pytest.approx(float(mean_col), abs=1e-6)
            std = math.sqrt(max(hv.sum_squares / hv.num - mean * mean, 0.0))
            assert std == pytest.approx(float(row[f"logr_std{suffix}_d{d}"]), rel=1e-3, abs=1e-7)
            assert hv.min < hv.max and np.isfinite([hv.min, hv.max]).all()  # a spread, not a constant
            # small events (the writer adds an empty bucket on the left), every sample counted
            assert len(hv.bucket) <= HISTOGRAM_BINS + 1 and sum(hv.bucket) == hv.num
        assert total == epochs * 1024, step  # every sample of every epoch counted (2 swimmers x 512 steps)


def test_per_dimension_tags_are_unchanged_from_earlier_runs():
    """Earlier runs' charts keep working: the tag of every column is what the log wrote before the layout."""
    columns = log_columns(TrainConfig())
    for column in columns:
        before = column.replace("_d", "/d", 1) if "_d" in column else column
        assert scalar_tag(column) == before, column
    assert scalar_tag("return_d12") == "return/d12" and scalar_tag("global_step") == "global_step"


def test_layout_of_columns_without_per_dimension_ones_is_empty():
    assert custom_scalars_layout(["global_step", "loss", "sps"]) == {}
    layout = custom_scalars_layout(["global_step", "return_d3", "return_d20", "widgets_d3"])
    assert layout == {
        "per chain length": {
            "return per chain length": ["Multiline", ["^return/d3$", "^return/d20$"]],
            "widgets per dimension": ["Multiline", ["^widgets/d3$"]],
        }
    }
