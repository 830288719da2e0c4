"""The two revolute joints hull-leg: ``b2RevoluteJoint`` with limit (3x3 block solve) and motor."""

from __future__ import annotations

import jax.numpy as jnp

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
    ca, sa = jnp.cos(aa), jnp.sin(aa)
    cb, sb = jnp.cos(ab), jnp.sin(ab)
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
        "rax": rax, "ray": ray, "rbx": rbx, "rby": rby, "state": state,
        "k13": k13, "k23": k23, "motor_mass": 1.0 / k33,
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


def joint_velocity(va, vb, j, k, imp, motor):
    """b2RevoluteJoint::SolveVelocityConstraints: motor, then limit (3x3 block) or point."""
    (vax, vay, wa), (vbx, vby, wb) = va, vb
    ma, mb, ia, ib = INV_MASS[0], INV_MASS[k + 1], INV_I[0], INV_I[k + 1]
    ix, iy, iz = imp
    new_m = jnp.clip(motor - j["motor_mass"] * (wb - wa - JOINT_MOTOR_SPEED[k]),
                     -JOINT_MAX_IMPULSE, JOINT_MAX_IMPULSE)
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
    clamp = ((state == LIMIT_AT_LOWER) & (iz + fz < 0)) | ((state == LIMIT_AT_UPPER) & (iz + fz > 0))
    dx = jnp.where(limited, jnp.where(clamp, rx, fx), px_)
    dy = jnp.where(limited, jnp.where(clamp, ry, fy), py_)
    dz = jnp.where(limited, jnp.where(clamp, -iz, fz), 0.0)
    new_imp = (ix + dx, iy + dy, iz + dz)
    vax, vay = vax - ma * dx, vay - ma * dy
    wa = wa - ia * (j["rax"] * dy - j["ray"] * dx + dz)
    vbx, vby = vbx + mb * dx, vby + mb * dy
    wb = wb + ib * (j["rbx"] * dy - j["rby"] * dx + dz)
    return (vax, vay, wa), (vbx, vby, wb), new_imp, new_m


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
