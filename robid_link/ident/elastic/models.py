"""Frequency-response models of an elastic joint (two-mass, a third mass on the arm, a coupled
pair, Coulomb friction on the arm by its describing function) and what a log adds to them: the
controller's hold of the torque over a sample and a delay between the logged torque and position.

Convention: G = q_m/τ (motor position over motor torque), joint units, s = jω.
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np

__all__ = ["two_mass_frf", "three_mass_frf", "motor_and_arm", "arm_coulomb_frf",
           "coupled_frf", "as_logged", "logged_with_derivatives", "logged_kernel",
           "LOGGED_PARAMETERS"]


def _arm(s: np.ndarray, ja: float, ba: float | np.ndarray, kg: float,
         third: tuple[float, float, float] | None) -> np.ndarray:
    """The arm's impedance (torque over position): Ja s² + Ba s + Kg, plus a third mass j3 on
    a spring k3 ∥ damper d3 when given."""
    arm = ja * s * s + ba * s + kg
    if third is not None:
        j3, k3, d3 = third
        z3 = d3 * s + k3
        arm = arm + z3 * j3 * s * s / (j3 * s * s + z3)
    return arm


def two_mass_frf(f_hz: np.ndarray, jm: float, ja: float, k: float, d: float, ba: float = 0.0,
                 kg: float = 0.0) -> np.ndarray:
    """G = qm/τ = (A + Z) / (Jm s² (A + Z) + Z A), arm A = Ja s² + Ba s + Kg, spring
    Z = D s + K; Kg the gravity stiffness ∂g/∂q of the arm at the pose (known from the rigid
    model). Ba = Kg = 0: (Ja s² + Z) / (s² (Jm Ja s² + (Jm + Ja) Z))."""
    return motor_and_arm(np.asarray(f_hz), jm, ja, k, d, ba, kg)[0]


def three_mass_frf(f_hz: np.ndarray, jm: float, ja: float, k: float, d: float, ba: float,
                   kg: float, j3: float, k3: float, d3: float) -> np.ndarray:
    """G of motor – spring – arm – spring k3 ∥ damper d3 – third mass j3 (a tool on a
    flexible flange, a second gear stage): the two-mass model with a second mode."""
    return motor_and_arm(np.asarray(f_hz), jm, ja, k, d, ba, kg, (j3, k3, d3))[0]


def motor_and_arm(f: np.ndarray, jm: float, ja: float, k: float, d: float,
                  ba: float | np.ndarray, kg: float,
                  third: tuple[float, float, float] | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The motor's and the arm's positions over the motor torque: (qm/τ, qa/τ)."""
    s = 2j * np.pi * np.asarray(f, dtype=float)
    z = d * s + k
    arm = _arm(s, ja, ba, kg, third)
    g = (arm + z) / (jm * s * s * (arm + z) + z * arm)
    return g, g * z / (arm + z)


def arm_coulomb_frf(f_hz: np.ndarray, jm: float, ja: float, k: float, d: float, ba: float,
                    kg: float, fc: float, tau_amp: np.ndarray, drift: np.ndarray,
                    third: tuple[float, float, float] | None = None) -> np.ndarray:
    """G with Coulomb friction ``fc`` on the arm, as its describing function at each step's
    torque amplitude and drift: the arm's velocity v0 + V sin ωt reverses when V > |v0|, and
    fc·sign(v) then has the fundamental (4 fc/π)·√(1 − (v0/V)²) in phase with the velocity:
    a damper c = (4 fc/(π V))·√(1 − (v0/V)²) on the arm, zero while the drift keeps it one-
    signed. V = ω·|qa/τ|·|T| depends on c: solved per step by bisection (c = c(V(c)))."""
    f = np.asarray(f_hz, dtype=float)
    w = 2 * np.pi * f
    v0 = np.maximum(np.abs(np.asarray(drift, dtype=float)), 1e-9)
    amp = np.asarray(tau_amp, dtype=float)

    def gap(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g, arm = motor_and_arm(f, jm, ja, k, d, ba + c, kg, third)
        v = w * np.abs(arm) * amp
        r = np.clip(v0 / np.maximum(v, 1e-300), 0.0, 1.0)
        return 4 * fc / np.pi * np.sqrt(1.0 - r * r) / np.maximum(v, 1e-300) - c, g

    # c(V) peaks at 2 fc/(π v0) (where V = √2 v0): the root lies below
    lo, hi = np.zeros_like(f), 2 * max(fc, 0.0) / (np.pi * v0) * 1.001 + 1e-12
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        up = gap(mid)[0] > 0
        lo, hi = np.where(up, mid, lo), np.where(up, hi, mid)
    return gap(0.5 * (lo + hi))[1]


def coupled_frf(f_hz: np.ndarray, jm: Sequence[float], ja: Sequence[float], jcop: float,
                k: Sequence[float], d: Sequence[float], ba: Sequence[float] = (0.0, 0.0),
                kg: np.ndarray | None = None) -> np.ndarray:
    """2×2 G (K, 2, 2): [Jm s² + Z − Z (A + Z)⁻¹ Z]⁻¹, A = [[Ja1, Jcop], [Jcop, Ja2]] s²
    + diag(Ba) s + Kg (2×2 gravity stiffness), Z = diag(D s + K)."""
    s = 2j * np.pi * np.asarray(f_hz)[:, None, None]
    eye = np.eye(2)
    z = (np.asarray(d)[None, :] * s[:, :, 0] + np.asarray(k)[None, :])[:, :, None] * eye
    jam = np.array([[ja[0], jcop], [jcop, ja[1]]])
    kgm = np.zeros((2, 2)) if kg is None else np.asarray(kg, dtype=float)
    arm = np.linalg.solve(jam * s * s + np.asarray(ba) * eye * s + kgm + z, z)
    dyn = np.asarray(jm)[:, None] * eye * s * s + z - z @ arm
    return np.linalg.inv(dyn)


def as_logged(f_hz: np.ndarray, g: np.ndarray, jm: float | Sequence[float], *,
              delay_s: float | Sequence[float] = 0.0, hold_s: float = 0.0) -> np.ndarray:
    """The FRF a log shows of the plant's G: with ``hold_s`` > 0 the logged torque is held
    over the sample (a controller at the log's rate), which delays it by half a sample and,
    with the response's images aliased back, scales the motor's high-frequency asymptote
    1/(Jm s²) by c = (ωh/2)² cos(ωh/2)/sin²(ωh/2) (the exact hold equivalent of 1/s²) instead
    of sinc(ωh/2); then a delay ``delay_s`` between the logged torque and position (a compute
    delay, encoder latency; negative when the logged torque lags the one acting). For a pair
    the delays are per torque (columns). G (K,) or (K, 2, 2)."""
    f = np.asarray(f_hz, dtype=float)
    w = 2 * np.pi * f
    pair = g.ndim == 3
    if hold_s > 0:
        x = 0.5 * w * hold_s
        sinc = np.sin(x) / x
        c = x * x * np.cos(x) / np.sin(x) ** 2
        motor = 1.0 / (-(w * w))
        if pair:
            asym = motor[:, None, None] * np.diag(1.0 / np.asarray(jm, dtype=float))[None]
            g = (g * sinc[:, None, None] + asym * (c - sinc)[:, None, None])
        else:
            g = g * sinc + motor / float(np.asarray(jm)) * (c - sinc)
        shift = np.exp(-1j * x)
        g = g * (shift[:, None, None] if pair else shift)
    if pair:
        tau = np.broadcast_to(np.asarray(delay_s, dtype=float), (2,))
        return g * np.exp(-1j * w[:, None, None] * tau[None, None, :])
    return g * np.exp(-1j * w * float(np.asarray(delay_s)))


#: the parameters of ``logged_with_derivatives``, in the order of its Jacobian's columns
LOGGED_PARAMETERS = ("jm", "ja", "k", "d", "ba", "delay_s", "j3", "f3", "z3")


def logged_with_derivatives(f_hz: np.ndarray, jm: float, ja: float, k: float, d: float,
                            ba: float, kg: float,
                            f3_z3_j3: tuple[float, float, float] | None = None, *,
                            delay_s: float = 0.0, hold_s: float = 0.0
                            ) -> tuple[np.ndarray, np.ndarray]:
    """The two- (three-) mass G as logged (``as_logged(motor_and_arm(…))``) and ∂ log G/∂p,
    (K, 6) or with a third mass (K, 9), columns p in the order of ``LOGGED_PARAMETERS`` (a third
    mass j3 on k3 = j3 (2π f3)², d3 = 2 z3 j3 (2π f3), given as ``f3_z3_j3`` = (f3, z3, j3)):
    the fit's model and Jacobian in one evaluation (numba). With G = N/D, N = A + Z,
    D = Jm s² N + Z A: ∂G = (∂N − G ∂D)/D; an arm term ∂A adds ∂A to N and ∂A (Jm s² + Z) to
    D, a spring term ∂Z adds ∂Z and ∂Z (Jm s² + A); Jm adds s² N to D (and −1/Jm² to the
    hold's 1/Jm term)."""
    w = 2 * np.pi * np.asarray(f_hz, dtype=float)
    third = f3_z3_j3 is not None
    f3, z3, j3 = f3_z3_j3 if f3_z3_j3 is not None else (0.0, 0.0, 0.0)
    g = np.empty(w.size, dtype=complex)
    dlog = np.empty((w.size, 9 if third else 6), dtype=complex)
    logged_kernel(w, hold_s, jm, ja, k, d, ba, kg, third, f3, z3, j3, delay_s, g, dlog)
    return g, dlog


@numba.njit(cache=True, nogil=True)
def logged_kernel(w, hold_s, jm, ja, k, d, ba, kg, third, f3, z3, j3, delay_s, g_out, d_out):
    """``logged_with_derivatives`` into ``g_out`` (K,) and ``d_out`` (K, 6 or 9) at the angular
    frequencies w: for numba code (the bounded fit evaluates it at every step)."""
    om = 2 * np.pi * f3
    for i in range(w.size):
        s = 1j * w[i]
        s2 = s * s
        z = d * s + k
        arm = ja * s2 + ba * s + kg
        q = om * om + 2 * z3 * om * s  # the third mass's spring: Z3 = j3·q
        if third:  # its share of the arm: T = j3 q s²/(s² + q)
            arm += j3 * q * s2 / (s2 + q)
        num = arm + z
        den = jm * s2 * num + z * arm
        g = num / den
        sinc, motor, shift = 1.0, 0.0, 0.0
        if hold_s > 0:
            x = 0.5 * w[i] * hold_s
            sinc = np.sin(x) / x
            motor = -(x * x * np.cos(x) / np.sin(x) ** 2 - sinc) / (w[i] * w[i])  # × 1/Jm
            shift = -x  # the hold's half sample
        held = g * sinc + motor / jm
        g_out[i] = held * np.exp(1j * (shift - w[i] * delay_s))
        scale = sinc / (den * held)
        per_arm, per_spring = scale * (1 - g * (jm * s2 + z)), scale * (1 - g * (jm * s2 + arm))
        d_out[i, 0] = -(scale * g * s2 * num + motor / (jm * jm * held))
        d_out[i, 1] = s2 * per_arm
        d_out[i, 2] = per_spring
        d_out[i, 3] = s * per_spring
        d_out[i, 4] = s * per_arm
        d_out[i, 5] = -1j * w[i]
        if third:
            t_q = j3 * s2 * s2 / (s2 + q) ** 2 * per_arm  # ∂T/∂q, in log G
            d_out[i, 6] = q * s2 / (s2 + q) * per_arm
            d_out[i, 7] = t_q * 2 * np.pi * (2 * om + 2 * z3 * s)
            d_out[i, 8] = t_q * 2 * om * s
