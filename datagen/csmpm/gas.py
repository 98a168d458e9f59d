"""The ideal gas of CSMPM (thesis eq. 3.9) and the exact solution of its Riemann problem.

Conserved variables per cell, stacked on the first axis: density rho, momentum rho u (one row
per dimension) and total energy per volume rho E = rho e + rho |u|^2 / 2, with the ideal-gas
equation of state p = (gamma - 1) rho e (gamma 1.4, air). :func:`exact_riemann` is the exact
solution of a 1D Riemann problem (Toro, *Riemann Solvers and Numerical Methods for Fluid
Dynamics*, ch. 4): the closed form the shock tubes are validated against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["GAMMA", "conserved", "primitive", "pressure", "sound_speed", "physical", "shock_state", "shock_start",
           "RiemannSolution", "exact_riemann"]

GAMMA = 1.4


def conserved(density, velocity, pressure, gamma: float = GAMMA) -> np.ndarray:
    """(d + 2, *cells) conserved variables of primitive fields: density (*cells), velocity
    (d, *cells), pressure (*cells)."""
    density, pressure = np.asarray(density, np.float64), np.asarray(pressure, np.float64)
    velocity = np.asarray(velocity, np.float64).reshape((-1,) + density.shape)
    energy = pressure / (gamma - 1.0) + 0.5 * density * np.sum(velocity ** 2, axis=0)
    return np.concatenate([density[None], density * velocity, energy[None]])


def pressure(state: np.ndarray, gamma: float = GAMMA) -> np.ndarray:
    """p = (gamma - 1) (rho E - |rho u|^2 / (2 rho)) of conserved ``state`` (d + 2, *cells)."""
    momentum = state[1:-1]
    return (gamma - 1.0) * (state[-1] - 0.5 * np.sum(momentum ** 2, axis=0) / state[0])


def primitive(state: np.ndarray, gamma: float = GAMMA) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(density, velocity (d, *cells), pressure) of conserved ``state``."""
    return state[0], state[1:-1] / state[0], pressure(state, gamma)


def sound_speed(density, pressure, gamma: float = GAMMA) -> np.ndarray:
    """c = sqrt(gamma p / rho)."""
    return np.sqrt(gamma * np.asarray(pressure) / np.asarray(density))


def physical(state: np.ndarray, gamma: float = GAMMA) -> bool:
    """Whether a conserved state (d + 2, ...) is finite with positive density and pressure."""
    return bool(np.all(np.isfinite(state)) and np.all(state[0] > 0) and np.all(pressure(state, gamma) > 0))


def shock_state(mach: float, rho: float, p: float, gamma: float = GAMMA) -> tuple[float, float, float]:
    """[rho, u, p] behind a shock of Mach ``mach`` moving into still gas (rho, p): the
    Rankine–Hugoniot jump conditions."""
    c = math.sqrt(gamma * p / rho)
    m2 = mach * mach
    return (rho * (gamma + 1.0) * m2 / ((gamma - 1.0) * m2 + 2.0), 2.0 * c * (m2 - 1.0) / ((gamma + 1.0) * mach),
            p * (1.0 + 2.0 * gamma / (gamma + 1.0) * (m2 - 1.0)))


def shock_start(x: np.ndarray, at: float, mach: float, ahead, gamma: float = GAMMA) -> tuple[np.ndarray, np.ndarray]:
    """A 2D channel's start with a shock of Mach ``mach`` at x = ``at`` moving towards +x into still
    gas ``ahead`` = (rho, p), cell centres' x coordinates ``x`` (nx, ny): (the conserved state
    behind it (4,), which an inlet keeps feeding; the conserved state (4, nx, ny))."""
    rho1, p1 = ahead
    rho2, u2, p2 = shock_state(mach, rho1, p1, gamma)
    behind = x < at
    state = conserved(np.where(behind, rho2, rho1), np.stack([np.where(behind, u2, 0.0), np.zeros_like(x)]),
                      np.where(behind, p2, p1), gamma)
    return conserved(np.array(rho2), np.array([u2, 0.0]), np.array(p2), gamma), state


@dataclass(frozen=True)
class RiemannSolution:
    """The star region of a Riemann problem (pressure, velocity, densities left and right of
    the contact) and where its waves are at time t: ``waves`` maps ``shock``,
    ``rarefaction_head``, ``rarefaction_tail`` and ``contact`` to speeds (per side: ``left_``
    and ``right_`` prefixes where the wave is on that side)."""

    p_star: float
    u_star: float
    rho_star_left: float
    rho_star_right: float
    waves: dict


def _side(p: float, rho: float, p_k: float, gamma: float) -> tuple[float, float]:
    """Toro's f_K(p) and its derivative: the velocity jump across the wave of side K."""
    c = np.sqrt(gamma * p_k / rho)
    if p > p_k:  # shock
        a, b = 2.0 / ((gamma + 1.0) * rho), (gamma - 1.0) / (gamma + 1.0) * p_k
        root = np.sqrt(a / (p + b))
        return (p - p_k) * root, root * (1.0 - 0.5 * (p - p_k) / (p + b))
    ratio = p / p_k  # rarefaction
    exponent = (gamma - 1.0) / (2.0 * gamma)
    return 2.0 * c / (gamma - 1.0) * (ratio ** exponent - 1.0), ratio ** (-(gamma + 1.0) / (2.0 * gamma)) / (rho * c)


def exact_riemann(left, right, x, t: float, interface: float = 0.0, gamma: float = GAMMA):
    """The exact solution at points ``x`` and time ``t`` > 0 of the Riemann problem ``left`` =
    (rho, u, p) for x < ``interface`` and ``right`` for x > it: (density, velocity, pressure)
    arrays like x, and the :class:`RiemannSolution`. ValueError where the states make a vacuum."""
    (rho_l, u_l, p_l), (rho_r, u_r, p_r) = (tuple(float(v) for v in s) for s in (left, right))
    if min(rho_l, rho_r, p_l, p_r) <= 0:
        raise ValueError(f"Riemann states need positive density and pressure, got left {left}, right {right}")
    c_l, c_r = np.sqrt(gamma * p_l / rho_l), np.sqrt(gamma * p_r / rho_r)
    if 2.0 * (c_l + c_r) / (gamma - 1.0) <= u_r - u_l:
        raise ValueError(f"the Riemann problem left {left}, right {right} creates a vacuum")
    p = max(1e-10, 0.5 * (p_l + p_r) - 0.125 * (u_r - u_l) * (rho_l + rho_r) * (c_l + c_r))  # Toro's PVRS guess
    for _ in range(100):
        (f_l, d_l), (f_r, d_r) = _side(p, rho_l, p_l, gamma), _side(p, rho_r, p_r, gamma)
        step = (f_l + f_r + u_r - u_l) / (d_l + d_r)
        new = max(p - step, 1e-3 * p)
        if abs(new - p) <= 1e-15 * (new + p):
            p = new
            break
        p = new
    (f_l, _), (f_r, _) = _side(p, rho_l, p_l, gamma), _side(p, rho_r, p_r, gamma)
    u = 0.5 * (u_l + u_r) + 0.5 * (f_r - f_l)
    g = (gamma - 1.0) / (gamma + 1.0)
    rho_sl = rho_l * ((p / p_l + g) / (g * p / p_l + 1.0) if p > p_l else (p / p_l) ** (1.0 / gamma))
    rho_sr = rho_r * ((p / p_r + g) / (g * p / p_r + 1.0) if p > p_r else (p / p_r) ** (1.0 / gamma))
    p, u, rho_sl, rho_sr = float(p), float(u), float(rho_sl), float(rho_sr)
    waves = {"contact": u}

    def mach(ratio):  # shock Mach number against the state ahead of it (Toro 4.52, 4.59)
        return math.sqrt((gamma + 1.0) / (2.0 * gamma) * ratio + (gamma - 1.0) / (2.0 * gamma))

    if p > p_l:
        waves["left_shock"] = u_l - c_l * mach(p / p_l)
    else:
        waves["left_rarefaction_head"] = u_l - c_l
        waves["left_rarefaction_tail"] = u - c_l * (p / p_l) ** ((gamma - 1.0) / (2.0 * gamma))
    if p > p_r:
        waves["right_shock"] = u_r + c_r * mach(p / p_r)
    else:
        waves["right_rarefaction_head"] = u_r + c_r
        waves["right_rarefaction_tail"] = u + c_r * (p / p_r) ** ((gamma - 1.0) / (2.0 * gamma))
    s = (np.asarray(x, np.float64) - interface) / t
    rho, vel, pres = np.empty_like(s), np.empty_like(s), np.empty_like(s)
    for side, (rho_k, u_k, p_k, c_k, rho_star), sign in (("left", (rho_l, u_l, p_l, c_l, rho_sl), -1.0),
                                                          ("right", (rho_r, u_r, p_r, c_r, rho_sr), 1.0)):
        here = s < u if side == "left" else s >= u
        if f"{side}_shock" in waves:
            outside = here & (sign * (s - waves[f"{side}_shock"]) > 0)
            fan = np.zeros_like(here)
        else:
            outside = here & (sign * (s - waves[f"{side}_rarefaction_head"]) > 0)
            fan = here & ~outside & (sign * (s - waves[f"{side}_rarefaction_tail"]) > 0)
        star = here & ~outside & ~fan
        rho[outside], vel[outside], pres[outside] = rho_k, u_k, p_k
        rho[star], vel[star], pres[star] = rho_star, u, p
        if fan.any():  # inside the fan: Toro (4.56) / (4.63)
            v = 2.0 / (gamma + 1.0) * (-sign * c_k + (gamma - 1.0) / 2.0 * u_k + s[fan])
            c = -sign * (v - s[fan])  # the fan's characteristics: s = v - c (left), v + c (right)
            rho[fan] = rho_k * (c / c_k) ** (2.0 / (gamma - 1.0))
            vel[fan], pres[fan] = v, p_k * (c / c_k) ** (2.0 * gamma / (gamma - 1.0))
    return (rho, vel, pres), RiemannSolution(p, u, rho_sl, rho_sr, waves)
