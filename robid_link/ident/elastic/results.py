"""The results of the elasticity fits: one joint's two-mass parameters (with what the fit found
in the log and the tests of its extensions) and a pair's coupled inertia."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from robid_link.ident.elastic.models import as_logged, motor_and_arm

__all__ = ["JointElasticity", "CoupledElasticity"]


@dataclass(frozen=True)
class JointElasticity:
    """Two-mass parameters of one joint (units of the log's side), with what the fit found in
    the log (``delay_s``, ``hold_s``) and the F-tests of the extensions (``tests``)."""

    joint: int
    jm: float
    ja: float
    k: float
    d: float
    std: dict[str, float]
    fit_rms: float  # RMS of the log-FRF residual (≈ relative error of the points)
    measures: str | None = None  # the campaign entry that measures it (set by the daemon)
    ba: float = 0.0  # viscous friction on the arm side (N·m·s/rad)
    kg: float = 0.0  # gravity stiffness of the arm at the pose (known, not fitted)
    fc: float | None = None  # Coulomb friction on the arm side (N·m); None: not in the model
    delay_s: float = 0.0  # the logged torque acts this much later than logged (fitted)
    hold_s: float = 0.0  # the torque held over a sample of this length (0: not held)
    third: tuple[float, float, float] | None = None  # (j3, k3, d3) of a third mass on the arm
    chi2: float = 1.0  # weighted residual over its degrees of freedom (≈ 1: fits to the noise)
    tests: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def f_res_hz(self) -> float:
        return math.sqrt(self.k * (self.jm + self.ja) / (self.jm * self.ja)) / (2 * math.pi)

    @property
    def f_antires_hz(self) -> float:
        return math.sqrt(self.k / self.ja) / (2 * math.pi)

    def model_frf(self, f_hz: np.ndarray, *, logged: bool = False) -> np.ndarray:
        """The fitted linear model's q_m/τ (the arm's Coulomb friction left out); ``logged``:
        as the log shows it (hold and delay)."""
        g = motor_and_arm(np.asarray(f_hz), self.jm, self.ja, self.k, self.d, self.ba,
                          self.kg, self.third)[0]
        return as_logged(f_hz, g, self.jm, delay_s=self.delay_s, hold_s=self.hold_s) \
            if logged else g

    def as_dict(self) -> dict[str, Any]:
        third = None if self.third is None else dict(zip(("j3", "k3", "d3"), self.third,
                                                         strict=True))
        return {"joint": self.joint, "jm": self.jm, "ja": self.ja, "k": self.k, "d": self.d,
                "ba": self.ba, "fc_arm": self.fc, "kg": self.kg, "f_res_hz": self.f_res_hz,
                "f_antires_hz": self.f_antires_hz,
                "std": dict(self.std), "fit_rms": self.fit_rms, "measures": self.measures,
                "delay_s": self.delay_s, "hold_s": self.hold_s, "third_mass": third,
                "chi2": self.chi2, "tests": {k: dict(v) for k, v in self.tests.items()}}


@dataclass(frozen=True)
class CoupledElasticity:
    joints: tuple[int, int]
    jcop: float
    std: dict[str, float]
    fit_rms: float
    kg: tuple[tuple[float, float], tuple[float, float]] = ((0.0, 0.0), (0.0, 0.0))

    def as_dict(self) -> dict[str, Any]:
        return {"joints": list(self.joints), "jcop": self.jcop, "std": dict(self.std),
                "fit_rms": self.fit_rms}
