"""What ``morph-train`` says while and after a run trains, read from the run's ``progress.csv``.

While it trains (the rows the trainer appends, read as it hands each over: ``on_row``, the trainer's row hook,
``algo.run.Run``): a warning line when an update's
approximate KL is far above the target, ``KL_WARN_FACTOR`` x ``kl_target`` (0.1 at the default 0.01), the
sign of a policy that left the data's policy far behind (a learning rate too high for it: the shipped
policy fine-tuned from bags at 0.01 reached KL 17 on its first update, 0.19 at 0.003). The first
``MAX_WARNINGS`` are said; the count of all of them is in the summary.

After it trains: a summary of two lines (steps and updates; the final training return, or the return of
the recorded episodes for a run trained from bags; where config.json, progress.csv and the checkpoints are).
"""

from __future__ import annotations

import csv
import io
import math
import sys
from pathlib import Path

from morph_core.algo.run_dir import RunDir

KL_WARN_FACTOR = 10.0
"""an update's approximate KL above KL_WARN_FACTOR x kl_target is warned about"""
MAX_WARNINGS = 3
"""KL warnings said while a run trains (the rest are counted in the summary)"""
RETURN_WINDOW = 50
"""episodes the final training return is the mean of (the progress bar's ``ret``)"""


def _float(text: str | None) -> float:
    try:
        return float(text)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return math.nan


class ProgressFollower:
    """Reads the rows a trainer appends to ``run_dir/progress.csv`` and warns about updates of this session
    (logged after ``start_step``: a resumed run's earlier rows were warned about when they were made) whose
    approximate KL exceeds ``kl_limit``. Made before the trainer starts: the file it finds then is an
    earlier session's and is not read (the trainer replaces it, cut at the checkpoint it resumes from)."""

    def __init__(
        self,
        run_dir: str | Path,
        kl_limit: float,
        start_step: int = 0,
        tool: str = "morph-train",
        hint: str = "a lower --learning-rate keeps it closer",
    ):
        self.files = RunDir(run_dir)
        self.path = self.files.progress
        self.kl_limit = kl_limit
        self.hint = hint
        self.start_step = start_step
        self.tool = tool
        self.rows: list[dict] = []
        """every row of the run"""
        self.session: list[dict] = []
        """the rows logged after ``start_step``: this session's"""
        self.high_kl: list[dict] = []
        self._file: tuple[int, int] | None = None  # (inode, offset read up to)
        try:  # the trainer puts a new file in place as it starts (a resumed run's cut at its checkpoint)
            self._before: int | None = self.path.stat().st_ino
        except FileNotFoundError:
            self._before = None
        self._header: list[str] | None = None
        self._seen: set[float] = set()
        self._warned = 0

    # -- reading -------------------------------------------------------------------------------------
    def poll(self) -> None:
        """Take the complete rows written since the last call (the file replaced, e.g. at a resume: from its
        start again)."""
        try:
            st = self.path.stat()
        except FileNotFoundError:
            return
        if st.st_ino == self._before:
            return  # the file of an earlier session, rows after its checkpoint included: not this run's yet
        inode, offset = self._file if self._file is not None else (st.st_ino, 0)
        if inode != st.st_ino or st.st_size < offset:
            # A new file (a resumed run's, cut at its checkpoint): what was read of the old one is gone.
            offset, self._header = 0, None
            self.rows, self.session, self.high_kl, self._seen = [], [], [], set()
        with self.path.open("rb") as f:
            f.seek(offset)
            chunk = f.read()
        end = chunk.rfind(b"\n") + 1  # complete lines only: a row being written is read next time
        self._file = (st.st_ino, offset + end)
        lines = chunk[:end].decode().splitlines()
        if self._header is None and lines:
            self._header, lines = next(csv.reader([lines[0]])), lines[1:]
        if not lines or self._header is None:
            return
        for row in csv.DictReader(io.StringIO("\n".join(lines)), fieldnames=self._header):
            step = _float(row.get("global_step"))
            if step not in self._seen:
                self._seen.add(step)
                self.rows.append(row)
                if step > self.start_step:
                    self.session.append(row)
                    self._check(row)

    def _check(self, row: dict) -> None:
        kl = _float(row.get("approx_kl"))
        if not kl > self.kl_limit:
            return
        self.high_kl.append(row)
        self._warned += 1
        if self._warned <= MAX_WARNINGS:
            more = " (further ones are counted, not said)" if self._warned == MAX_WARNINGS else ""
            self._say(
                f"{self.tool}: warning: update {row.get('iteration')} (step {row.get('global_step')}): approximate "
                f"KL {kl:.3g} > {self.kl_limit:g} ({KL_WARN_FACTOR:g}x kl_target): the policy moved far from the "
                f"one that acted; {self.hint}{more}"
            )

    @staticmethod
    def _say(text: str) -> None:
        # the bar only when asked
        from tqdm import tqdm

        tqdm.write(text, file=sys.stderr)  # above a progress bar, which is drawn again below it

    # -- following a run -------------------------------------------------------------------------------
    def on_row(self, row: dict, saved: bool) -> None:
        """The trainer's row hook (``train(on_row=...)``): the row just written is read, with any before it (a
        resumed run's earlier rows), and warned about as it comes."""
        self.poll()

    def __enter__(self) -> ProgressFollower:
        return self

    def __exit__(self, *exc) -> None:
        self.poll()  # the last rows

    # -- the end ---------------------------------------------------------------------------------------
    def summary(self, run_dir: str | Path, data: bool = False) -> list[str]:
        """Two lines on the run (``data``: trained from recorded data, whose return is the recording's)."""
        run_dir = Path(run_dir)
        if not self.session:
            head = f"{self.tool}: no update in this session"
        else:
            last = self.rows[-1]
            head = f"{self.tool}: done: step {last['global_step']} (update {last['iteration']})"
            if data:
                head += f"; return of the recorded episodes {_float(last.get('return_mean')):.1f}"
            else:
                mean, episodes = self.training_return()
                head += f"; training return {mean:.1f} (mean of its last {episodes} episodes)" if episodes else (
                    "; no episode finished yet")  # fmt: skip
            head += f"; last update's approximate KL {_float(last.get('approx_kl')):.3g}"
            if self.high_kl:
                top = max(_float(r["approx_kl"]) for r in self.high_kl)
                head += (
                    f"; {len(self.high_kl)} of {len(self.session)} updates above KL {self.kl_limit:g} (max {top:.3g})"
                )
        files = RunDir(run_dir)
        where = f"{self.tool}: files in {run_dir}: {files.config.name}, {files.progress.name}"
        if files.tensorboard.is_dir():
            where += f", {files.tensorboard.name}/"
        checkpoints = [path for _, path in files.saved_checkpoints()]
        if checkpoints:
            where += f", {files.checkpoints.name}/ ({len(checkpoints)}, the last {checkpoints[-1].name})"
        if files.state.exists():
            where += f", {files.state.name} (for --resume)"
        return [head, where]

    def training_return(self) -> tuple[float, int]:
        """The mean return of the run's last ``RETURN_WINDOW`` episodes, as near as the rows tell
        (each row: the mean over its ``episodes``), and how many episodes that is."""
        total, count = 0.0, 0
        for row in reversed(self.rows):
            n, mean = _float(row.get("episodes")), _float(row.get("return_mean"))
            if not n > 0 or math.isnan(mean):
                continue
            take = min(int(n), RETURN_WINDOW - count)
            total, count = total + mean * take, count + take
            if count >= RETURN_WINDOW:
                break
        return (total / count if count else math.nan), count
