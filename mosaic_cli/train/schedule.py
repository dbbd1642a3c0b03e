"""The paper's step learning-rate schedule, scaled to any step count.

The paper multiplies the learning rate by 0.1 every 100k of BASE's 300k iterations and every
30k of the fine-tunes' 90k: both are decays at 1/3 and 2/3 of the run.  The rate is a pure
function of the step, so a resumed run needs no scheduler state to continue exactly.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class StepSchedule:
    lr: float
    steps: int
    milestones: tuple[float, ...] = (1 / 3, 2 / 3)
    decay: float = 0.1

    @property
    def milestone_steps(self) -> tuple[int, ...]:
        return tuple(int(round(m * self.steps)) for m in self.milestones)

    def lr_at(self, step: int) -> float:
        """The learning rate for 0-based ``step``."""
        passed = sum(step >= s for s in self.milestone_steps)
        return self.lr * self.decay**passed

    def describe(self) -> str:
        points = ", ".join(str(s) for s in self.milestone_steps)
        return f"lr {self.lr:g}, x{self.decay:g} at steps {points}"
