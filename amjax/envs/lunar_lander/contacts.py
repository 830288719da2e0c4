"""Leg-ground contacts: ``b2ContactSolver`` velocity constraints (friction, 2-point block solver) and position
correction, one manifold at a time, written with scalars so that vmap keeps every operation elementwise."""

from __future__ import annotations

import jax.numpy as jnp

from amjax.envs.lunar_lander.collide import sin_cos
from amjax.envs.lunar_lander.constants import (
    BAUMGARTE,
    BODY_FRICTION,
    INV_I,
    INV_MASS,
    LINEAR_SLOP,
    LOCAL_CENTER,
    MAX_CONDITION_NUMBER,
    MAX_LINEAR_CORRECTION,
    POLYGON_RADIUS,
)


# The solver below is written with scalars only (vectors are (x, y) tuples): under vmap every
# operation is elementwise over the batch, which lets XLA fuse the 180-iteration loop body.
def _body_origin(cx, cy, a, b):
    sa, ca = sin_cos(a)
    lx, ly = LOCAL_CENTER[b]
    return cx - (ca * lx - sa * ly), cy - (sa * lx + ca * ly), ca, sa


def contact_constraint(b, cnt, face_a, ln, lp, lps, c, a):
    """b2ContactSolver::InitializeVelocityConstraints for one manifold (edge A static)."""
    m, i_ = INV_MASS[b], INV_I[b]
    r = POLYGON_RADIUS
    px, py, ca, sa = _body_origin(c[0], c[1], a, b)
    bnx, bny = ca * ln[0] - sa * ln[1], sa * ln[0] + ca * ln[1]
    bpx, bpy = ca * lp[0] - sa * lp[1] + px, sa * lp[0] + ca * lp[1] + py
    nx = jnp.where(face_a, ln[0], -bnx)
    ny = jnp.where(face_a, ln[1], -bny)
    rs = []
    for j in range(2):
        qx, qy = lps[j, 0], lps[j, 1]
        # faceA: clip point on the body, plane on the edge (world coordinates).
        kx, ky = ca * qx - sa * qy + px, sa * qx + ca * qy + py
        da = r - ((kx - lp[0]) * ln[0] + (ky - lp[1]) * ln[1])
        ax_ = 0.5 * ((kx + da * ln[0]) + (kx - r * ln[0]))
        ay_ = 0.5 * ((ky + da * ln[1]) + (ky - r * ln[1]))
        # faceB: clip point on the edge, plane on the body.
        db = r - ((qx - bpx) * bnx + (qy - bpy) * bny)
        bx_ = 0.5 * ((qx - r * bnx) + (qx + db * bnx))
        by_ = 0.5 * ((qy - r * bny) + (qy + db * bny))
        rs.append((jnp.where(face_a, ax_, bx_) - c[0], jnp.where(face_a, ay_, by_) - c[1]))
    (r1x, r1y), (r2x, r2y) = rs
    rn1, rn2 = r1x * ny - r1y * nx, r2x * ny - r2y * nx
    rt1, rt2 = -r1x * nx - r1y * ny, -r2x * nx - r2y * ny
    k11, k22, k12 = m + i_ * rn1 * rn1, m + i_ * rn2 * rn2, m + i_ * rn1 * rn2
    kt1, kt2 = m + i_ * rt1 * rt1, m + i_ * rt2 * rt2
    det = k11 * k22 - k12 * k12
    well = k11 * k11 < MAX_CONDITION_NUMBER * det
    inv_det = jnp.where(det != 0, 1.0 / det, det)
    return {
        "b": b,
        "pcount": cnt,
        "vcount": jnp.where((cnt == 2) & ~well, 1, cnt),
        "nx": nx,
        "ny": ny,
        "r1x": r1x,
        "r1y": r1y,
        "r2x": r2x,
        "r2y": r2y,
        "rn1": rn1,
        "rn2": rn2,
        "nm1": jnp.where(k11 > 0, 1.0 / k11, 0.0),
        "nm2": jnp.where(k22 > 0, 1.0 / k22, 0.0),
        "tm1": jnp.where(kt1 > 0, 1.0 / kt1, 0.0),
        "tm2": jnp.where(kt2 > 0, 1.0 / kt2, 0.0),
        "k11": k11,
        "k12": k12,
        "k22": k22,
        "ki11": inv_det * k22,
        "ki12": -inv_det * k12,
        "ki22": inv_det * k11,
        "face_a": face_a,
        "lnx": ln[0],
        "lny": ln[1],
        "lpx": lp[0],
        "lpy": lp[1],
        "q1x": lps[0, 0],
        "q1y": lps[0, 1],
        "q2x": lps[1, 0],
        "q2y": lps[1, 1],
    }


def contact_velocity(v, k, ni1, ni2, ti1, ti2):
    """b2ContactSolver::SolveVelocityConstraints for one manifold (friction, then normal)."""
    vx, vy, w = v
    m, i_ = INV_MASS[k["b"]], INV_I[k["b"]]
    nx, ny = k["nx"], k["ny"]
    tx, ty = ny, -nx
    fr = BODY_FRICTION[k["b"]]
    tis = [ti1, ti2]
    nis = [ni1, ni2]
    for j, (rx, ry, tm) in enumerate(((k["r1x"], k["r1y"], k["tm1"]), (k["r2x"], k["r2y"], k["tm2"]))):
        vt = (vx - w * ry) * tx + (vy + w * rx) * ty
        max_f = fr * nis[j]
        new = jnp.clip(tis[j] - tm * vt, -max_f, max_f)
        act = k["vcount"] > j
        lam = jnp.where(act, new - tis[j], 0.0)
        tis[j] = jnp.where(act, new, tis[j])
        vx, vy = vx + m * lam * tx, vy + m * lam * ty
        w = w + i_ * lam * (rx * ty - ry * tx)
    vn1 = (vx - w * k["r1y"]) * nx + (vy + w * k["r1x"]) * ny
    vn2 = (vx - w * k["r2y"]) * nx + (vy + w * k["r2x"]) * ny
    one = jnp.maximum(ni1 - k["nm1"] * vn1, 0.0)
    # Two points: Box2D's block solver, total enumeration of the 2-d LCP.
    b1 = vn1 - (k["k11"] * ni1 + k["k12"] * ni2)
    b2 = vn2 - (k["k12"] * ni1 + k["k22"] * ni2)
    x1a = -(k["ki11"] * b1 + k["ki12"] * b2)
    x1b = -(k["ki12"] * b1 + k["ki22"] * b2)
    x2a = -k["nm1"] * b1
    x3b = -k["nm2"] * b2
    c1 = (x1a >= 0) & (x1b >= 0)
    c2 = (x2a >= 0) & (k["k12"] * x2a + b2 >= 0)
    c3 = (x3b >= 0) & (k["k12"] * x3b + b1 >= 0)
    c4 = (b1 >= 0) & (b2 >= 0)
    n1 = jnp.where(c1, x1a, jnp.where(c2, x2a, jnp.where(c3 | c4, 0.0, ni1)))
    n2 = jnp.where(c1, x1b, jnp.where(c3, x3b, jnp.where(c2 | c4, 0.0, ni2)))
    two, single = k["vcount"] == 2, k["vcount"] == 1
    new1 = jnp.where(two, n1, jnp.where(single, one, ni1))
    new2 = jnp.where(two, n2, ni2)
    d1, d2 = new1 - ni1, new2 - ni2
    vx, vy = vx + m * nx * (d1 + d2), vy + m * ny * (d1 + d2)
    w = w + i_ * (d1 * k["rn1"] + d2 * k["rn2"])
    return (vx, vy, w), new1, new2, tis[0], tis[1]


def contact_position(cx, cy, a, k, j):
    """b2ContactSolver::SolvePositionConstraints for point j; returns new (cx, cy, a), sep."""
    b = k["b"]
    m, i_ = INV_MASS[b], INV_I[b]
    px, py, ca, sa = _body_origin(cx, cy, a, b)
    qx, qy = (k["q1x"], k["q1y"]) if j == 0 else (k["q2x"], k["q2y"])
    lnx, lny, lpx, lpy = k["lnx"], k["lny"], k["lpx"], k["lpy"]
    # faceA
    kx, ky = ca * qx - sa * qy + px, sa * qx + ca * qy + py
    sep_a = (kx - lpx) * lnx + (ky - lpy) * lny - 2 * POLYGON_RADIUS
    # faceB
    bnx, bny = ca * lnx - sa * lny, sa * lnx + ca * lny
    bpx, bpy = ca * lpx - sa * lpy + px, sa * lpx + ca * lpy + py
    sep_b = (qx - bpx) * bnx + (qy - bpy) * bny - 2 * POLYGON_RADIUS
    fa = k["face_a"]
    nx, ny = jnp.where(fa, lnx, -bnx), jnp.where(fa, lny, -bny)
    ptx, pty = jnp.where(fa, kx, qx), jnp.where(fa, ky, qy)
    sep = jnp.where(fa, sep_a, sep_b)
    corr = jnp.clip(BAUMGARTE * (sep + LINEAR_SLOP), -MAX_LINEAR_CORRECTION, 0.0)
    rn = (ptx - cx) * ny - (pty - cy) * nx
    kk = m + i_ * rn * rn
    act = k["pcount"] > j
    imp = jnp.where(act & (kk > 0), -corr / kk, 0.0)
    return cx + m * imp * nx, cy + m * imp * ny, a + i_ * imp * rn, jnp.where(act, sep, 0.0)
