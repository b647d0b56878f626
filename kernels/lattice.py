"""The marching lattice: the step rule, its warped coordinate and runs of intervals.

Step rule. Samples partition the ray's range [t0, t1] (box entry clamped to `near`, box exit
clamped to `far`) into intervals whose length follows instant-ngp's cone rule
``dt = clamp(t * cone_angle, dt_min, dt_max)``. To make the rule skippable, the lattice is
defined by a warped coordinate u(t) with du/dt = 1/dt(t):

    t < dt_min/cone                 : u grows by 1 every dt_min      (constant steps)
    dt_min/cone <= t < dt_max/cone  : t grows by (1 + cone) per unit u (dt = cone·t)
    t >= dt_max/cone                : u grows by 1 every dt_max      (constant steps)

Interval k of a ray spans u in [k + j - 1, k + j] (j = the ray's jitter in [0, 1), 0 without)
clipped to [t0, t1]; its step is exactly clamp(t_k·cone, dt_min, dt_max) except the one step
that straddles a phase change. Because the lattice is a closed form of k, the first interval
whose midpoint passes a given t is found in O(1) (`run_end`): the march uses it to jump over
an empty cell and to take an occupied cell's samples as one run.
"""

from __future__ import annotations

import functools
import math

import warp as wp


@wp.struct
class StepRule:
    """dt = clamp(t * cone, a, b); L = log1p(cone); t1p = a / cone, t2p = b / cone; the
    reciprocals spare the loop its divisions."""

    a: float
    b: float
    L: float
    inv_a: float
    inv_b: float
    inv_L: float
    t1p: float
    t2p: float


@wp.struct
class Lattice:
    """One ray's lattice: phase boundaries of the step rule in t (x1, x2) and in u (u1, u2),
    measured from the ray's start t0; jm1 = jitter - 1. Precomputed once per ray so that a
    lattice point costs one compare and one fma (phase 2: an exp)."""

    t0: float
    jm1: float
    u1: float
    u2: float
    x1: float
    x2: float


@wp.func
def make_lattice(rule: StepRule, t0: float, jm1: float) -> Lattice:
    """The lattice of a ray that starts at t0 with jitter jm1 + 1 (phase boundaries in t, u)."""
    lat = Lattice()
    lat.t0 = t0
    lat.jm1 = jm1
    lat.x1 = wp.max(t0, rule.t1p)
    lat.u1 = (lat.x1 - t0) * rule.inv_a
    lat.x2 = wp.max(lat.x1, rule.t2p)
    lat.u2 = lat.u1
    if lat.x1 < lat.x2:
        lat.u2 = lat.u1 + wp.log(lat.x2 / lat.x1) * rule.inv_L
    return lat


@wp.func
def u_of(rule: StepRule, lat: Lattice, t: float) -> float:
    """Warped distance u from the ray's t0 to t >= t0, in steps (see module docstring)."""
    if t <= lat.x1:
        return (t - lat.t0) * rule.inv_a
    if t <= lat.x2:
        return lat.u1 + wp.log(t / lat.x1) * rule.inv_L
    return lat.u2 + (t - lat.x2) * rule.inv_b


@wp.func
def t_of(rule: StepRule, lat: Lattice, u: float) -> float:
    """Inverse of u_of: the t that lies u steps past t0 (t0 for u <= 0)."""
    if u <= 0.0:
        return lat.t0
    if u <= lat.u1:
        return lat.t0 + u * rule.a
    if u <= lat.u2:
        return lat.x1 * wp.exp((u - lat.u1) * rule.L)
    return lat.x2 + (u - lat.u2) * rule.b


@wp.func
def lattice_point(rule: StepRule, lat: Lattice, m: int) -> float:
    """Lattice point m of a ray, t(m + j - 1); interval k is [P(k), P(k + 1)] clipped to
    [t0, t1]. One expression for every use, so neighbours share their end exactly."""
    return t_of(rule, lat, float(m) + lat.jm1)


@wp.func
def in_run(rule: StepRule, lat: Lattice, k: int, t1: float, end: float) -> bool:
    """Interval k starts before t1 and its midpoint (its end clipped to t1) lies before `end`."""
    ta = lattice_point(rule, lat, k)
    if ta >= t1:
        return False
    return 0.5 * (ta + wp.min(lattice_point(rule, lat, k + 1), t1)) < end


@wp.func
def run_end(rule: StepRule, lat: Lattice, k: int, k_hi: int, t1: float, end: float) -> int:
    """The first interval after k that is not `in_run` (at most k_hi): every interval from k + 1
    up to it has its midpoint before `end`. A closed-form guess from u(min(end, t1)), then
    corrected by the predicate itself, so it equals stepping interval by interval wherever the
    lattice points are strictly increasing in float32 (the march takes runs only there)."""
    u_end = u_of(rule, lat, wp.min(end, t1)) - lat.jm1
    kk = wp.min(wp.max(k + 1, int(wp.min(u_end, 1.0e9))), k_hi)
    while kk < k_hi and in_run(rule, lat, kk, t1, end):
        kk += 1
    while kk > k + 1 and not in_run(rule, lat, kk - 1, t1, end):
        kk -= 1
    return kk


@functools.lru_cache(maxsize=64)
def step_rule(cone_angle: float, dt_min: float, dt_max: float) -> StepRule:
    """The Warp struct for dt = clamp(t * cone_angle, dt_min, dt_max) (cached: do not mutate)."""
    if not (dt_min > 0 and dt_max >= dt_min and cone_angle >= 0):
        raise ValueError(
            f"need dt_min > 0, dt_max >= dt_min, cone_angle >= 0; got {dt_min}, {dt_max}, "
            f"{cone_angle}"
        )
    rule = StepRule()
    rule.a = float(dt_min)
    rule.b = float(dt_max)
    if cone_angle > 0:
        rule.L = math.log1p(cone_angle)
        rule.t1p = dt_min / cone_angle
        rule.t2p = dt_max / cone_angle
    else:
        rule.L = 1.0
        rule.t1p = rule.t2p = 1e30
    rule.inv_a, rule.inv_b, rule.inv_L = 1.0 / rule.a, 1.0 / rule.b, 1.0 / rule.L
    return rule
