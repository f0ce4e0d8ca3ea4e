"""Input schedules: the signals that drive a model (insertion speed, shaft rotation, omega_B, ...).

Each input of the model is given in the config under ``inputs.<name>`` as a number (constant), a list
(constant vector) or one of the signal kinds below. Schedules are open loop and the same for every run;
depth (inserted length) is the time integral of the model's insertion input.
"""

from __future__ import annotations

from typing import Annotated, Literal, Union

import numpy as np
from pydantic import Field, model_validator

from needlecli.schema import NonNeg, Positive, Strict

Value = float | list[float]


class ConstantSignal(Strict):
    """The same value at every time (a number or a list given for an input is one)."""

    kind: Literal["constant"] = "constant"
    value: Value = Field(description="the input's value for the whole run, in the input's unit (a list for an input "
                                     "of several components); `inputs.<name>: 1.5` is short for this")


class PiecewiseSignal(Strict):
    """Values at given times, held (``interp: step``) or interpolated (``linear``) in between."""

    kind: Literal["piecewise"]
    times: list[NonNeg] = Field(min_length=1, description="knot times, s, strictly increasing (the first value also "
                                                       "holds before the first time)")
    values: list[Value] = Field(min_length=1, description="the input's value at each knot, in the input's unit (one "
                                                        "entry per time; a list per entry for a vector input)")
    interp: Literal["step", "linear"] = Field("step", description="step: hold each value until the next time; "
                                                                  "linear: interpolate between knots")

    @model_validator(mode="after")
    def _check(self):
        if len(self.times) != len(self.values):
            raise ValueError(f"times has {len(self.times)} entries but values has {len(self.values)}")
        if any(b <= a for a, b in zip(self.times, self.times[1:])):
            raise ValueError("times must increase strictly")
        sizes = {np.size(v) for v in self.values}
        if len(sizes) > 1:
            raise ValueError("values must all have the same size")
        return self


class FlipSignal(Strict):
    """180 deg shaft rotations (or any ``angle``) at given depths or times, at ``rate`` rad/s, on top of
    a constant ``base`` rate. The high-gain observer paper flips at chosen depths; the multi-rate UKF paper (fig. 7) turns once at 25 s."""

    kind: Literal["flips"]
    at_depths: list[NonNeg] | None = Field(None, description="inserted depths at which a flip starts, model length "
                                                         "unit, increasing (give this or at_times)")
    at_times: list[NonNeg] | None = Field(None, description="times at which a flip starts, s, increasing (give this "
                                                        "or at_depths)")
    angle: float = Field(np.pi, description="rotation per flip, rad (sign gives the direction)")
    rate: Positive = Field(np.pi, description="rotation speed during a flip, rad/s")
    base: float = Field(0.0, description="rotation speed outside flips, rad/s")

    @model_validator(mode="after")
    def _check(self):
        if (self.at_depths is None) == (self.at_times is None):
            raise ValueError("give exactly one of at_depths, at_times")
        marks = self.at_depths if self.at_depths is not None else self.at_times
        if any(b < a for a, b in zip(marks, marks[1:])):
            raise ValueError("flip depths/times must be in increasing order")
        return self


PlainSignal = Annotated[Union[ConstantSignal, PiecewiseSignal, FlipSignal], Field(discriminator="kind")]


def as_signal(v):
    """Plain numbers and lists are constant signals."""
    if isinstance(v, (int, float, list)) and not isinstance(v, bool):
        return {"kind": "constant", "value": v}
    if isinstance(v, dict) and v.get("kind") == "cases" and isinstance(v.get("cases"), list):
        return {**v, "cases": [as_signal(c) for c in v["cases"]]}
    return v


class CasesSignal(Strict):
    """Different schedules for different runs: run ``i`` follows case ``i mod len(cases)`` (the multi-rate UKF paper
    Fig. 7 compares rotation schedules this way). Not for the insertion input, whose integral is the
    depth shared by all runs."""

    kind: Literal["cases"]
    cases: list[PlainSignal] = Field(min_length=1, description="one schedule per case (a number, a list, or a "
                                                             "constant, piecewise or flips signal); run i follows "
                                                             "case i mod len(cases)")
    labels: list[str] | None = Field(None, description="a name per case for tables and legends (default: a "
                                                       "description of each schedule)")

    @model_validator(mode="after")
    def _check(self):
        if self.labels is not None and len(self.labels) != len(self.cases):
            raise ValueError(f"labels has {len(self.labels)} entries for {len(self.cases)} cases")
        if len({signal_size(c) for c in self.cases}) > 1:
            raise ValueError("all cases must have the same size")
        return self

    def case_labels(self) -> list[str]:
        return list(self.labels) if self.labels is not None else [describe(c) for c in self.cases]


Signal = Annotated[Union[ConstantSignal, PiecewiseSignal, FlipSignal, CasesSignal], Field(discriminator="kind")]


def describe(sig) -> str:
    """A short label of a signal for legends and tables."""
    if isinstance(sig, ConstantSignal):
        return f"constant {sig.value}"
    if isinstance(sig, PiecewiseSignal):
        return f"piecewise ({len(sig.times)} knots, {sig.interp})"
    if isinstance(sig, FlipSignal):
        at = f"at depths {sig.at_depths}" if sig.at_depths is not None else f"at t = {sig.at_times}"
        return f"flips {at}"
    return sig.kind


def signal_size(sig) -> int:
    if isinstance(sig, CasesSignal):
        return signal_size(sig.cases[0])
    if isinstance(sig, ConstantSignal):
        return int(np.size(sig.value))
    if isinstance(sig, PiecewiseSignal):
        return int(np.size(sig.values[0]))
    return 1


def evaluate_signal(sig, time: np.ndarray, depth: np.ndarray | None) -> np.ndarray:
    """Samples ``(T, size)`` of a signal on the grid ``time`` (``(K, T, size)`` for K cases);
    ``depth (T,)`` for depth-triggered kinds."""
    T = len(time)
    if isinstance(sig, CasesSignal):
        return np.stack([evaluate_signal(c, time, depth) for c in sig.cases])
    if isinstance(sig, ConstantSignal):
        return np.broadcast_to(np.atleast_1d(np.asarray(sig.value, dtype=float)), (T, signal_size(sig))).copy()
    if isinstance(sig, PiecewiseSignal):
        tk = np.asarray(sig.times, dtype=float)
        vk = np.asarray(sig.values, dtype=float).reshape(len(tk), -1)
        if sig.interp == "linear":
            return np.stack([np.interp(time, tk, vk[:, j]) for j in range(vk.shape[1])], -1)
        i = np.searchsorted(tk, time + 1e-12, side="right") - 1
        return vk[np.clip(i, 0, None)]  # the first value also holds before the first time
    # flips
    dt = float(time[1] - time[0]) if T > 1 else 1.0
    duration = abs(sig.angle) / sig.rate
    if sig.at_times is not None:
        starts = np.asarray(sig.at_times, dtype=float)
    else:
        if depth is None:
            raise ValueError("depth-triggered flips need the insertion input")
        marks = np.asarray(sig.at_depths, dtype=float)
        k = np.searchsorted(depth, marks - 1e-12, side="left")
        starts = np.where(k < T, time[np.clip(k, 0, T - 1)], np.inf)
    u = np.full(T, float(sig.base))
    speed = np.sign(sig.angle) * sig.rate
    for s in starts:  # loop over flips (a handful), not over runs
        if not np.isfinite(s):
            continue
        # each step k covers [t_k, t_k + dt): the rotation it gets is the overlap with [s, s + duration)
        overlap = np.clip(np.minimum(time + dt, s + duration) - np.maximum(time, s), 0.0, dt) / dt
        u = u + speed * overlap
    return u[:, None]
