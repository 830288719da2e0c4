"""The two revolute joints hull-leg: ``b2RevoluteJoint`` with limit (3x3 block solve) and motor."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from amjax.envs.lunar_lander.collide import sin_cos
from amjax.envs.lunar_lander.constants import (
    ANGULAR_SLOP,
    INV_I,
    INV_MASS,
    JOINT_ANCHOR_B,
    JOINT_LOWER,
    JOINT_MAX_IMPULSE,
    JOINT_MOTOR_SPEED,
    JOINT_REFERENCE,
    JOINT_UPPER,
    LIMIT_AT_LOWER,
    LIMIT_AT_UPPER,
    LIMIT_INACTIVE,
    LINEAR_SLOP,
    LOCAL_CENTER,
    MAX_ANGULAR_CORRECTION,
)


def _joint_arms(aa, ab, k):
    """World lever arms of joint k: r_A (hull origin - hull centre), r_B (anchor on the leg)."""
    sa, ca = sin_cos(aa)
    sb, cb = sin_cos(ab)
    lx, ly = -LOCAL_CENTER[0, 0], -LOCAL_CENTER[0, 1]
    bx, by = JOINT_ANCHOR_B[k]
    return ca * lx - sa * ly, sa * lx + ca * ly, cb * bx - sb * by, sb * bx + cb * by


def joint_constraint(aa, ab, k, limit_state):
    """b2RevoluteJoint::InitVelocityConstraints (K matrix, limit state)."""
    ma, mb, ia, ib = INV_MASS[0], INV_MASS[k + 1], INV_I[0], INV_I[k + 1]
    rax, ray, rbx, rby = _joint_arms(aa, ab, k)
    angle = ab - aa - JOINT_REFERENCE[k]
    state = jnp.where(
        angle <= JOINT_LOWER[k], LIMIT_AT_LOWER, jnp.where(angle >= JOINT_UPPER[k], LIMIT_AT_UPPER, LIMIT_INACTIVE)
    )
    k11 = ma + mb + ray * ray * ia + rby * rby * ib
    k12 = -ray * rax * ia - rby * rbx * ib
    k13 = -ray * ia - rby * ib
    k22 = ma + mb + rax * rax * ia + rbx * rbx * ib
    k23 = rax * ia + rbx * ib
    k33 = ia + ib
    # K is constant during the iterations: pre-invert it (b2Mat33::Solve33 / Solve22 algebra).
    ex, ey, ez = (k11, k12, k13), (k12, k22, k23), (k13, k23, k33)
    rows = [_cross3(ey, ez), _cross3(ez, ex), _cross3(ex, ey)]
    det = ex[0] * rows[0][0] + ex[1] * rows[0][1] + ex[2] * rows[0][2]
    det = jnp.where(det != 0, 1.0 / det, det)
    det2 = k11 * k22 - k12 * k12
    det2 = jnp.where(det2 != 0, 1.0 / det2, det2)
    return {
        "rax": rax,
        "ray": ray,
        "rbx": rbx,
        "rby": rby,
        "state": state,
        "k13": k13,
        "k23": k23,
        "motor_mass": 1.0 / k33,
        "inv3": [[det * r for r in row] for row in rows],
        "inv2": (det2 * k22, -det2 * k12, det2 * k11),
        "changed": state != limit_state,
    }


def _cross3(u, v):
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


def _solve22(a11, a12, a22, bx, by):
    det = a11 * a22 - a12 * a12
    det = jnp.where(det != 0, 1.0 / det, det)
    return det * (a22 * bx - a12 * by), det * (a11 * by - a12 * bx)


def joint_velocity(va, vb, j, k, imp, motor, pattern=None):
    """b2RevoluteJoint::SolveVelocityConstraints: motor, then limit (3x3 block) or point.

    Returns the bodies' velocities, the accumulated impulses and the ``pattern`` of the solve: the motor's clamp
    (0 none, 1 at +max, 2 at -max) and whether the limit's one-sided impulse was clamped. Given a ``pattern`` the
    solve takes those branches instead of testing them: an affine map of velocities and impulses.
    """
    (vax, vay, wa), (vbx, vby, wb) = va, vb
    ma, mb, ia, ib = INV_MASS[0], INV_MASS[k + 1], INV_I[0], INV_I[k + 1]
    ix, iy, iz = imp
    free_m = motor - j["motor_mass"] * (wb - wa - JOINT_MOTOR_SPEED[k])
    if pattern is None:
        motor_clamp = jnp.where(free_m > JOINT_MAX_IMPULSE, 1, jnp.where(free_m < -JOINT_MAX_IMPULSE, 2, 0))
    else:
        motor_clamp = pattern[0]
    new_m = jnp.where(motor_clamp == 1, JOINT_MAX_IMPULSE, jnp.where(motor_clamp == 2, -JOINT_MAX_IMPULSE, free_m))
    dm = new_m - motor
    wa, wb = wa - ia * dm, wb + ib * dm
    c1x = vbx - wb * j["rby"] - vax + wa * j["ray"]
    c1y = vby + wb * j["rbx"] - vay - wa * j["rax"]
    c2 = wb - wa
    fx, fy, fz = (-(r[0] * c1x + r[1] * c1y + r[2] * c2) for r in j["inv3"])
    i11, i12, i22 = j["inv2"]
    bx, by = -c1x + iz * j["k13"], -c1y + iz * j["k23"]
    rx, ry = i11 * bx + i12 * by, i12 * bx + i22 * by
    px_, py_ = -(i11 * c1x + i12 * c1y), -(i12 * c1x + i22 * c1y)
    state = j["state"]
    limited = state != LIMIT_INACTIVE
    if pattern is None:
        clamp = ((state == LIMIT_AT_LOWER) & (iz + fz < 0)) | ((state == LIMIT_AT_UPPER) & (iz + fz > 0))
    else:
        clamp = pattern[1]
    dx = jnp.where(limited, jnp.where(clamp, rx, fx), px_)
    dy = jnp.where(limited, jnp.where(clamp, ry, fy), py_)
    dz = jnp.where(limited, jnp.where(clamp, -iz, fz), 0.0)
    new_imp = (ix + dx, iy + dy, iz + dz)
    vax, vay = vax - ma * dx, vay - ma * dy
    wa = wa - ia * (j["rax"] * dy - j["ray"] * dx + dz)
    vbx, vby = vbx + mb * dx, vby + mb * dy
    wb = wb + ib * (j["rbx"] * dy - j["rby"] * dx + dz)
    return (vax, vay, wa), (vbx, vby, wb), new_imp, new_m, (motor_clamp, clamp & limited)


def joint_position(ca_, aa, cb_, ab, state, k):
    """b2RevoluteJoint::SolvePositionConstraints; returns positions and the converged flag."""
    ma, mb, ia, ib = INV_MASS[0], INV_MASS[k + 1], INV_I[0], INV_I[k + 1]
    angle = ab - aa - JOINT_REFERENCE[k]
    c_low, c_up = angle - JOINT_LOWER[k], angle - JOINT_UPPER[k]
    mm = 1.0 / (ia + ib)
    lim_low = -mm * jnp.clip(c_low + ANGULAR_SLOP, -MAX_ANGULAR_CORRECTION, 0.0)
    lim_up = -mm * jnp.clip(c_up - ANGULAR_SLOP, 0.0, MAX_ANGULAR_CORRECTION)
    lim = jnp.where(state == LIMIT_AT_LOWER, lim_low, jnp.where(state == LIMIT_AT_UPPER, lim_up, 0.0))
    ang_err = jnp.where(state == LIMIT_AT_LOWER, -c_low, jnp.where(state == LIMIT_AT_UPPER, c_up, 0.0))
    aa, ab = aa - ia * lim, ab + ib * lim
    rax, ray, rbx, rby = _joint_arms(aa, ab, k)
    ex = cb_[0] + rbx - ca_[0] - rax
    ey = cb_[1] + rby - ca_[1] - ray
    pos_err = jnp.sqrt(ex * ex + ey * ey)
    k11 = ma + mb + ia * ray * ray + ib * rby * rby
    k12 = -ia * rax * ray - ib * rbx * rby
    k22 = ma + mb + ia * rax * rax + ib * rbx * rbx
    ix, iy = _solve22(k11, k12, k22, ex, ey)
    ix, iy = -ix, -iy
    ca_ = (ca_[0] - ma * ix, ca_[1] - ma * iy)
    aa = aa - ia * (rax * iy - ray * ix)
    cb_ = (cb_[0] + mb * ix, cb_[1] + mb * iy)
    ab = ab + ib * (rbx * iy - rby * ix)
    return ca_, aa, cb_, ab, (pos_err <= LINEAR_SLOP) & (ang_err <= ANGULAR_SLOP)


# -- The joints' fixed point in one solve (free flight: no contact constraints in the island).
#
# With no contact rows, the 180 Gauss-Seidel sweeps of the two joints converge towards the solution of a small
# mixed linear complementarity problem: per joint, the point rows (2, equalities) and one angular row whose impulse
# is the motor's (|m| <= JOINT_MAX_IMPULSE, drives w_B - w_A to the motor speed) plus the limit's (one-sided, only
# while the limit is active). Per joint the angular row is in one of four modes at the solution:
#   A: motor unsaturated, limit slack: w_B - w_A = speed, angular impulse = m, |m| <= M;
#   B: limit holding, motor saturated towards its speed: w_B - w_A = 0, angular impulse = sign(speed) M + z;
#   C+/C-: motor saturated at +M / -M, limit slack: no angular equality.
# All 4 x 4 combinations are solved at once (one 6x6 symmetric positive definite system each) and the one that
# satisfies its inequalities is kept: Box2D's own total enumeration for two-point contacts, applied to the joints.
_MODE_A, _MODE_B, _MODE_CPLUS, _MODE_CMINUS = 0, 1, 2, 3
_COMBOS = np.array([(m0, m1) for m0 in range(4) for m1 in range(4)], np.int32)  # (16, 2)
_INFEASIBLE = np.float32(1e30)


def _solve_spd(a, b):
    """Solve ``a x = b`` for a small symmetric positive definite ``a`` (lists of arrays), unrolled LDL^T."""
    n = len(b)
    low = [[None] * n for _ in range(n)]
    diag = [None] * n
    for i in range(n):
        for j in range(i):
            s = a[i][j] - sum(low[i][k] * low[j][k] * diag[k] for k in range(j))
            low[i][j] = s / diag[j]
        diag[i] = a[i][i] - sum(low[i][k] * low[i][k] * diag[k] for k in range(i))
    y = []
    for i in range(n):
        y.append(b[i] - sum(low[i][k] * y[k] for k in range(i)))
    x = [None] * n
    for i in reversed(range(n)):
        x[i] = y[i] / diag[i] - sum(low[k][i] * x[k] for k in range(i + 1, n))
    return x


def solve_joints_exact(bodies, joints):
    """The two joints' velocity constraints solved to their fixed point (no contacts).

    ``bodies``: (vx, vy, w) of hull, leg 0, leg 1 after integrating forces, before any warm start; ``joints``:
    ``joint_constraint`` of each leg. Returns the bodies' velocities, the joints' accumulated (x, y, limit)
    impulses and motor impulses, as Gauss-Seidel returns them once converged.
    """
    ma, ia = INV_MASS[0], INV_I[0]
    mode = [jnp.asarray(_COMBOS[:, k]) for k in range(2)]
    big = JOINT_MAX_IMPULSE
    # Rows per joint k: point x, point y, angular; Jacobian on the hull (A) and on leg k (B).
    jac_a, jac_b = [], []
    for j in joints:
        jac_a += [(-1.0, 0.0, j["ray"]), (0.0, -1.0, -j["rax"]), (0.0, 0.0, -1.0)]
        jac_b += [(1.0, 0.0, -j["rby"]), (0.0, 1.0, j["rbx"]), (0.0, 0.0, 1.0)]
    weights = [(ma, ma, ia)] + [(INV_MASS[k + 1], INV_MASS[k + 1], INV_I[k + 1]) for k in range(2)]

    def dot_w(u, v, w):
        return u[0] * v[0] * w[0] + u[1] * v[1] * w[1] + u[2] * v[2] * w[2]

    # Delassus matrix J W J^T: each joint's block is Box2D's K; the joints couple through the hull.
    mat = [[None] * 6 for _ in range(6)]
    for r in range(6):
        for s in range(r + 1):
            value = dot_w(jac_a[r], jac_a[s], weights[0])
            if r // 3 == s // 3:
                value = value + dot_w(jac_b[r], jac_b[s], weights[1 + r // 3])
            mat[r][s] = mat[s][r] = value
    velocity = [
        dot_w(jac_a[r], bodies[0], (1.0, 1.0, 1.0)) + dot_w(jac_b[r], bodies[1 + r // 3], (1.0, 1.0, 1.0))
        for r in range(6)
    ]
    # Per combination: angular rows either free (target velocity) or fixed (a saturated motor's impulse).
    free, fixed, target = [], [], []
    for k in range(2):
        speed = JOINT_MOTOR_SPEED[k]
        free.append((mode[k] == _MODE_A) | (mode[k] == _MODE_B))
        fixed.append(jnp.where(mode[k] == _MODE_CPLUS, big, -big))
        target.append(jnp.where(mode[k] == _MODE_A, speed, 0.0))
    rhs = []
    for r in range(6):
        value = -velocity[r][..., None]
        if r % 3 == 2:
            value = jnp.where(free[r // 3], target[r // 3] + value, fixed[r // 3])
        for k in range(2):  # a fixed angular impulse moves to the right-hand side of the other rows
            if r != 3 * k + 2:
                value = value - jnp.where(free[k], 0.0, mat[r][3 * k + 2][..., None] * fixed[k])
        rhs.append(value)
    system = [[mat[r][s][..., None] for s in range(6)] for r in range(6)]
    for k in range(2):
        row = 3 * k + 2
        for s in range(6):
            off = 1.0 if s == row else 0.0
            system[row][s] = jnp.where(free[k], system[row][s], off)
            system[s][row] = jnp.where(free[k], system[s][row], off)
    impulse = _solve_spd(system, rhs)  # six arrays (..., 16)

    # Velocities of every combination, the angular ones checked against each mode's inequalities.
    def moved(body, jac, rows):
        return [
            bodies[body][i][..., None] + weights[body][i] * sum(jac[r][i] * impulse[r] for r in rows) for i in range(3)
        ]

    out_a = moved(0, jac_a, range(6))
    out_b = [moved(1 + k, jac_b, range(3 * k, 3 * k + 3)) for k in range(2)]
    violation = jnp.zeros_like(impulse[0])
    limit_z, motor = [], []
    for k, j in enumerate(joints):
        speed = JOINT_MOTOR_SPEED[k]
        saturated = np.float32(np.sign(speed)) * big
        ang = impulse[3 * k + 2]
        rel = out_b[k][2] - out_a[2]
        scale = j["motor_mass"][..., None]
        lower = (j["state"] == LIMIT_AT_LOWER)[..., None]
        upper = (j["state"] == LIMIT_AT_UPPER)[..., None]
        limited = lower | upper
        z = ang - saturated
        slack_ok = jnp.where(lower, jnp.maximum(-rel, 0.0), 0.0) + jnp.where(upper, jnp.maximum(rel, 0.0), 0.0)
        # A (limit slack at the motor's speed) is impossible where that speed drives into the active limit.
        v_a = jnp.where(lower if speed < 0 else upper, _INFEASIBLE, jnp.maximum(jnp.abs(ang) - big, 0.0))
        v_b = jnp.where(limited, jnp.where(lower, jnp.maximum(-z, 0.0), jnp.maximum(z, 0.0)), _INFEASIBLE)
        v_cp = scale * (jnp.maximum(rel - speed, 0.0) + slack_ok)
        v_cm = scale * (jnp.maximum(speed - rel, 0.0) + slack_ok)
        m = mode[k]
        violation = violation + jnp.where(
            m == _MODE_A, v_a, jnp.where(m == _MODE_B, v_b, jnp.where(m == _MODE_CPLUS, v_cp, v_cm))
        )
        limit_z.append(jnp.where(m == _MODE_B, z, 0.0))
        motor.append(jnp.where(m == _MODE_A, ang, jnp.where(m == _MODE_B, saturated, fixed[k])))

    pick = jax.nn.one_hot(jnp.argmin(violation, axis=-1), len(_COMBOS), dtype=violation.dtype)

    def chosen(x):
        return jnp.sum(x * pick, axis=-1)

    hull = tuple(chosen(x) for x in out_a)
    legs = [tuple(chosen(x) for x in out_b[k]) for k in range(2)]
    impulses = [(chosen(impulse[3 * k]), chosen(impulse[3 * k + 1]), chosen(limit_z[k])) for k in range(2)]
    return (hull, legs[0], legs[1]), impulses, [chosen(m) for m in motor]
