"""The progress bar of `sqjax segment` and `sqjax demo` (tqdm, on stderr when it is a terminal)."""

from __future__ import annotations

import sys


class Progress:
    """A progress bar on stderr (only when it is a terminal), with a total and an ETA (tqdm).

    Units are growth steps plus one unit per final stage (rejoining split parts and the final selection)
    of each round: `max_steps` growth steps and that stage per round, `1 + reseed` rounds. The total is an
    upper bound that shrinks to the truth as rounds end early, so the ETA errs long.

    `segment()` calls `progress(step, n_active, n_models)` after each growth step; this class also takes
    the keywords `stage` ("grow", "merge", "select", "reseed", "finish"), `round` (0-based) and `total`
    (the true number of units) should `segment()` pass them, and then uses them as given.
    """

    def __init__(self, max_steps: int, stream=None, enabled: bool | None = None, *, rounds: int = 1):
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled if enabled is not None else bool(getattr(self.stream, "isatty", lambda: False)())
        self.budget, self.rounds = max(int(max_steps), 1), max(int(rounds), 1)
        self.round, self.round_start, self.step, self.in_final = 0, 0, 0, False
        self.n_models, self.bar = 1 << 62, None

    @property
    def total(self) -> int:
        """Units still possible: steps done + the rest of this round's budget + later rounds + final stages."""
        done_rounds_steps = self.round_start
        this_round = self.step - self.round_start if self.in_final else self.budget
        return done_rounds_steps + this_round + (self.rounds - self.round - 1) * self.budget + self.rounds

    def _open(self, what: str):
        if self.bar is None and self.enabled:
            from tqdm import tqdm

            self.bar = tqdm(
                total=self.total,
                desc=f"sqjax: {what}",
                file=self.stream,
                unit="step",
                dynamic_ncols=True,
                leave=False,
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}] {postfix}",
            )

    def start(self, what: str):
        self._open(what)
        self._post("seeding (the first run compiles the kernels)")

    def _post(self, text: str):
        if self.bar is not None:
            self.bar.set_postfix_str(text, refresh=True)

    def _sync(self, total=None):
        if self.bar is not None:
            self.bar.total = int(total) if total is not None else self.total
            done = min(self.step + self.round, self.bar.total)  # a final stage per finished round
            if done > self.bar.n:
                self.bar.update(done - self.bar.n)  # update(): tqdm's smoothed rate, so the ETA forgets compiling
            else:
                self.bar.refresh()

    def __call__(
        self,
        step: int,
        n_active: int,
        n_models: int,
        *,
        stage: str | None = None,
        round: int | None = None,
        total: int | None = None,
    ):  # noqa: A002
        if round is not None and round != self.round:
            self.round, self.round_start, self.in_final = int(round), self.step, False
        elif stage in (None, "grow") and step > self.step and (self.in_final or n_models > self.n_models):
            # growth again after a final stage, or more models than selection left (reseeded ones
            # joined): a reseed round
            self.round, self.round_start, self.in_final = min(self.round + 1, self.rounds - 1), self.step, False
        self.step, self.n_models = int(step), int(n_models)
        stage = stage or ("grow" if n_active and self.step - self.round_start < self.budget else "merge")
        if stage != "grow":
            self.in_final = True
        self._sync(total)
        where = f"round {self.round + 1}/{self.rounds}, " if self.rounds > 1 else ""
        tail = (
            f"{n_active} of {n_models} models growing"
            if stage == "grow"
            else "merging split parts, final selection"
            if stage in ("merge", "select")
            else stage
        )
        self._post(f"{where}growth step {self.step - self.round_start}/{self.budget}, {tail}")

    def phase(self, what: str):
        self._post(what)

    def close(self):
        if self.bar is not None:
            self.bar.n = self.bar.total
            self.bar.close()
            self.bar = None
