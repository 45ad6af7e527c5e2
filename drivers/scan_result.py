"""What a scan run did: ScanResult, its counts, timings and one-line summary."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class ScanResult:
    """What a scan run did."""

    out_dir: Path
    manifest: Path
    total: int
    resumed: int = 0  # positions already complete when this run started
    captured: int = 0  # positions completed by this run
    retries: int = 0
    reconnects: dict[str, int] = field(default_factory=lambda: {"stage": 0, "camera": 0})
    warnings: int = 0
    rejected: int = 0  # frames that could not be inspected, captured again
    failed: list[str] = field(default_factory=list)  # labels of positions whose frames could not be inspected
    inspected: int = 0
    inspect_failures: int = 0
    verdict_failed: list[str] = field(default_factory=list)  # labels of inspected positions whose verdict is FAIL
    elapsed_s: float = 0.0  # the whole run, device opening included
    loop_s: float = 0.0  # time in the position loop
    motion_s: float = 0.0  # move + settle inside the loop
    home_s: float = 0.0

    @property
    def done(self) -> int:
        return self.resumed + self.captured

    @property
    def all_passed(self) -> bool:
        """Every position recorded inspectable, and (with inspection) inspected with a PASS verdict."""
        return not (self.failed or self.verdict_failed or self.inspect_failures)

    @property
    def positions_per_s_excl_motion(self) -> float:
        """Positions completed per second of loop time not spent moving or settling."""
        busy = self.loop_s - self.motion_s
        return self.captured / busy if busy > 0 else math.nan

    def summary(self) -> str:
        """One line for the CLI."""
        rate = self.positions_per_s_excl_motion
        rate_text = f"{rate:.1f} positions/s excluding motion" if math.isfinite(rate) else "no positions captured"
        return (f"scan complete: {self.done} of {self.total} positions in {self.out_dir} "
                f"({self.captured} captured now, {self.resumed} already done, {self.retries} retries, "
                f"{self.reconnects['stage']} stage and {self.reconnects['camera']} camera reconnects, "
                f"{self.warnings} frame warnings, {self.rejected} uninspectable frames captured again)"
                f"{self._failed_text()}{self._verdict_text()}; {self.elapsed_s:.1f} s in all, {self.motion_s:.1f} s moving and "
                f"settling, {rate_text}")

    def _failed_text(self) -> str:
        """The failed positions for the summary line ('' if none): the operator must see them."""
        if not self.failed:
            return ""
        plural = "s" if len(self.failed) != 1 else ""
        return f"; {len(self.failed)} position{plural} FAILED (frames not inspectable: {_shown(self.failed)})"

    def _verdict_text(self) -> str:
        """The inspected positions and those whose QC verdict is FAIL ('' without inspection)."""
        if not (self.inspected or self.inspect_failures):
            return ""
        text = f"; {self.inspected} frames inspected"
        if self.inspect_failures:
            text += f", {self.inspect_failures} could not be"
        if self.verdict_failed:
            n = len(self.verdict_failed)
            text += f", QC verdict FAIL at {n} position{'s' if n != 1 else ''} ({_shown(self.verdict_failed)})"
        return text


def _shown(labels: list[str], most: int = 10) -> str:
    """Position labels for a summary line, the first `most` of them."""
    return ", ".join(labels[:most]) + (", ..." if len(labels) > most else "")
