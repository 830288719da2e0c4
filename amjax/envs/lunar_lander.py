"""Gymnasium's LunarLander-v3 in pure JAX (gymnax API).

The game logic follows Gymnasium's ``gymnasium/envs/box2d/lunar_lander.py`` (v1.3.0, MIT) and
the physics is a small port of the parts of Box2D 2.3 (pybox2d 2.3.10, zlib) that the game
uses: three bodies (hull, two legs), two revolute joints with limit and motor, edge-polygon
contacts against the ten terrain edges, the sequential-impulse solver (180 velocity / 60
position iterations) and the island sleep rule. Constants cite the file they come from.

Exact (to float32 rounding; see ``docs/lunar_lander.md`` for measured differences):
terrain, observation, reward, termination and action decoding; engine impulse geometry,
wind, initial push; semi-implicit Euler with Box2D's velocity/position clamps; the revolute
joints with limit and motor, so free flight including the reset-step leg snap matches Box2D.

Same algorithm as Box2D, but not step-exact once legs touch the ground (TOI, below): contact
manifolds (``b2CollideEdgeAndPolygon`` without ghost vertices), the contact solver (friction,
2-point block solver, warm starting by contact id, position correction), Begin/End contact
events and the island sleep rule (all bodies slow for 0.5 s and positions solved).

Approximate (measured sizes in docs/lunar_lander.md):
- no time-of-impact (TOI) sub-stepping: a fast body may sink up to ``v * dt`` into the ground
  before the next step's contact pushes it out, and Begin/End contact events fire at the next
  step's collide instead of inside the TOI sub-step (a one-step lag of a leg flag or of
  game_over on fast impacts);
- hull-ground contacts are detected (game_over) but not solved: Gymnasium ends the episode on
  the hull's first contact, so only that final observation differs;
- each leg is solved against the (at most two) terrain edges under its x-range; the y=0
  bottom edge is not modelled (the terrain lies on or above it);
- contact order inside the solver, and the order of simultaneous Begin/End events of one leg,
  follow the edge index rather than Box2D's linked lists.
The random draws are explicit inputs of :func:`reset_from_draws` / :func:`step_from_draws`;
numpy's PCG64 stream itself is not reproduced, only the distributions.
"""

from __future__ import annotations

import importlib.util
import math
import os
from types import ModuleType
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from gymnax.environments import environment, spaces

# --- Gymnasium lunar_lander.py constants ---------------------------------------------------
FPS = 50
SCALE = 30.0
MAIN_ENGINE_POWER = 13.0
SIDE_ENGINE_POWER = 0.6
INITIAL_RANDOM = 1000.0
LANDER_POLY = [(-14, 17), (-17, 0), (-17, -10), (17, -10), (17, 0), (14, 17)]
LEG_AWAY = 20
LEG_DOWN = 18
LEG_W, LEG_H = 2, 8
LEG_SPRING_TORQUE = 40
SIDE_ENGINE_HEIGHT = 14
SIDE_ENGINE_AWAY = 12
MAIN_ENGINE_Y_LOCATION = 4
VIEWPORT_W, VIEWPORT_H = 600, 400
W = VIEWPORT_W / SCALE
H = VIEWPORT_H / SCALE
CHUNKS = 11
HELIPAD_Y = H / 4
N_EDGES = CHUNKS - 1

# --- Box2D 2.3 b2Settings.h ------------------------------------------------------------------
DT = np.float32(1.0 / FPS)  # world.Step(1/FPS, 6*30, 2*30)
VELOCITY_ITERATIONS = 6 * 30
POSITION_ITERATIONS = 2 * 30
B2_PI = np.float32(3.14159265359)
LINEAR_SLOP = np.float32(0.005)
ANGULAR_SLOP = np.float32(2.0 / 180.0) * B2_PI
POLYGON_RADIUS = np.float32(2.0) * LINEAR_SLOP
MAX_LINEAR_CORRECTION = np.float32(0.2)
MAX_ANGULAR_CORRECTION = np.float32(8.0 / 180.0) * B2_PI
MAX_TRANSLATION = np.float32(2.0)
MAX_ROTATION = np.float32(0.5) * B2_PI
BAUMGARTE = np.float32(0.2)
TIME_TO_SLEEP = np.float32(0.5)
LINEAR_SLEEP_TOL = np.float32(0.01)
ANGULAR_SLEEP_TOL = np.float32(2.0 / 180.0) * B2_PI
MAX_CONDITION_NUMBER = np.float32(1000.0)  # b2ContactSolver.cpp block solver

# Contact feature ids (b2Collision.h: e_vertex = 0, e_face = 1), packed like b2ContactID.key.
_VERTEX, _FACE = 0, 1
_ILLEGAL_KEY = -1

# Friction mixing sqrt(fA * fB) (b2Contact.h); ground edges 0.1, hull 0.1, legs 0.2 (default).
_HULL_FRICTION = np.sqrt(np.float32(0.1) * np.float32(0.1))
_LEG_FRICTION = np.sqrt(np.float32(0.2) * np.float32(0.1))
BODY_FRICTION = np.array([_HULL_FRICTION, _LEG_FRICTION, _LEG_FRICTION], np.float32)


def _hull(points: list[tuple[float, float]]) -> np.ndarray:
    """Vertex order of b2PolygonShape::Set (gift wrapping from the right-most point)."""
    ps = np.asarray(points, np.float32)
    i0 = 0
    for i in range(1, len(ps)):
        if ps[i, 0] > ps[i0, 0] or (ps[i, 0] == ps[i0, 0] and ps[i, 1] < ps[i0, 1]):
            i0 = i
    hull, ih = [], i0
    while True:
        hull.append(ih)
        ie = 0
        for j in range(1, len(ps)):
            if ie == ih:
                ie = j
                continue
            r, v = ps[ie] - ps[hull[-1]], ps[j] - ps[hull[-1]]
            c = r[0] * v[1] - r[1] * v[0]
            if c < 0 or (c == 0 and v @ v > r @ r):
                ie = j
        ih = ie
        if ie == i0:
            return ps[hull]


def _normals(verts: np.ndarray) -> np.ndarray:
    edge = np.roll(verts, -1, axis=0) - verts
    n = np.stack([edge[:, 1], -edge[:, 0]], axis=1)
    return (n / np.linalg.norm(n, axis=1, keepdims=True)).astype(np.float32)


def _mass(verts: np.ndarray, density: float) -> tuple[float, np.ndarray, float]:
    """b2PolygonShape::ComputeMass + b2Body::ResetMassData: mass, local centre, I about it."""
    v = verts.astype(np.float64)
    s = v.mean(axis=0)
    e1, e2 = v - s, np.roll(v, -1, axis=0) - s
    d = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    area = 0.5 * d.sum()
    center = ((0.5 * d / 3.0)[:, None] * (e1 + e2)).sum(axis=0) / area
    intx2 = e1[:, 0] ** 2 + e2[:, 0] * e1[:, 0] + e2[:, 0] ** 2
    inty2 = e1[:, 1] ** 2 + e2[:, 1] * e1[:, 1] + e2[:, 1] ** 2
    inertia = density * ((0.25 / 3.0 * d) * (intx2 + inty2)).sum()
    mass = density * area
    inertia_origin = inertia + mass * ((center + s) @ (center + s) - center @ center)
    local_center = center + s
    return mass, local_center, inertia_origin - mass * local_center @ local_center


LANDER_VERTS = _hull([(x / SCALE, y / SCALE) for x, y in LANDER_POLY])
LEG_VERTS = np.array(
    [[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float32
) * np.array([LEG_W / SCALE, LEG_H / SCALE], np.float32)  # b2PolygonShape::SetAsBox order
LANDER_NORMALS, LEG_NORMALS = _normals(LANDER_VERTS), _normals(LEG_VERTS)
_m_l, _c_l, _i_l = _mass(LANDER_VERTS, 5.0)
_m_g, _c_g, _i_g = _mass(LEG_VERTS, 1.0)
LANDER_CENTROID = _c_l.astype(np.float32)
# Bodies are indexed [hull, legs[0] (i=-1), legs[1] (i=+1)] as in Gymnasium.
INV_MASS = np.array([1 / _m_l, 1 / _m_g, 1 / _m_g], np.float32)
INV_I = np.array([1 / _i_l, 1 / _i_g, 1 / _i_g], np.float32)
LOCAL_CENTER = np.array([_c_l, [0, 0], [0, 0]], np.float32)
LEG_SIGN = (-1, 1)
# Revolute joints (Gymnasium: localAnchorA=(0,0), localAnchorB=(i*LEG_AWAY, LEG_DOWN)/SCALE,
# limits [0.4, 0.9] for i=-1 and [-0.9, -0.4] for i=+1, motor speed 0.3*i, torque 40).
JOINT_ANCHOR_B = np.array([[i * LEG_AWAY / SCALE, LEG_DOWN / SCALE] for i in LEG_SIGN], np.float32)
JOINT_LOWER = np.array([0.9 - 0.5, -0.9], np.float32)
JOINT_UPPER = np.array([0.9, -0.9 + 0.5], np.float32)
JOINT_MOTOR_SPEED = np.array([0.3 * i for i in LEG_SIGN], np.float32)
# pybox2d's revoluteJointDef sets referenceAngle = bodyB.angle - bodyA.angle (Box2D_joints.i).
JOINT_REFERENCE = np.array([i * 0.05 for i in LEG_SIGN], np.float32)
JOINT_MAX_IMPULSE = DT * np.float32(LEG_SPRING_TORQUE)
# Box2D's island is built depth-first from the newest body (legs[1]), so joint 1 is solved
# before joint 0 and leg 1's contacts come first (b2World::Solve).
JOINT_ORDER = (1, 0)
CONTACT_BODY_ORDER = (2, 1)  # legs only: a hull contact ends the episode (game_over)
# Limit states of b2RevoluteJoint.
_INACTIVE, _AT_LOWER, _AT_UPPER = 0, 1, 2

OBS_LOW = np.array([-2.5, -2.5, -10.0, -10.0, -2 * math.pi, -10.0, -0.0, -0.0], np.float32)
OBS_HIGH = np.array([2.5, 2.5, 10.0, 10.0, 2 * math.pi, 10.0, 1.0, 1.0], np.float32)


@struct.dataclass
class EnvParams(environment.EnvParams):
    """Gymnasium constructor arguments (all traced: vmappable, not baked into the program)."""

    gravity: float = -10.0
    enable_wind: bool = False
    wind_power: float = 15.0
    turbulence_power: float = 1.5
    max_steps_in_episode: int = 1000


@struct.dataclass
class EnvState(environment.EnvState):
    """Box2D world state. Body axis: [hull, legs[0], legs[1]]; edge axis: 10 terrain edges."""

    pos: jax.Array  # (3, 2) centres of mass (b2Sweep.c)
    angle: jax.Array  # (3,)
    vel: jax.Array  # (3, 2) centre-of-mass velocities
    omega: jax.Array  # (3,)
    joint_impulse: jax.Array  # (2, 3) revolute warm-start impulse (point x, point y, limit)
    motor_impulse: jax.Array  # (2,)
    limit_state: jax.Array  # (2,) int32, b2LimitState
    sleep_time: jax.Array  # (3,)
    contact_edge: jax.Array  # (3, 2) int32 the two edges under each body (-1: none)
    touching: jax.Array  # (3, 2) bool, b2Contact touching flag of those (body, edge) pairs
    contact_key: jax.Array  # (3, 2, 2) int32 manifold point ids (b2ContactID.key)
    normal_impulse: jax.Array  # (3, 2, 2) warm-start impulses per manifold point
    tangent_impulse: jax.Array  # (3, 2, 2)
    leg_contact: jax.Array  # (2,) bool, Gymnasium's leg.ground_contact
    game_over: jax.Array  # bool
    awake: jax.Array  # bool
    terrain_y: jax.Array  # (11,) smooth_y
    prev_shaping: jax.Array
    wind_idx: jax.Array  # int32
    torque_idx: jax.Array  # int32
    time: int


def validate_params(params: EnvParams) -> None:
    """Raise ValueError for arguments Gymnasium rejects or warns about (concrete values only)."""
    checks = (
        ("gravity", params.gravity, -12.0, 0.0, "the open interval (-12, 0)"),
        ("wind_power", params.wind_power, 0.0, 20.0, "[0, 20]"),
        ("turbulence_power", params.turbulence_power, 0.0, 2.0, "[0, 2]"),
    )
    for name, value, lo, hi, allowed in checks:
        try:
            arr = np.asarray(value, dtype=np.float64)
        except jax.errors.TracerArrayConversionError as err:
            raise ValueError(f"validate_params needs concrete values, {name} is traced") from err
        bad = ~np.isfinite(arr)
        if name == "gravity":
            bad |= (arr <= lo) | (arr >= hi)
        else:
            bad |= (arr < lo) | (arr > hi)
        if np.any(bad):
            raise ValueError(f"LunarLander {name}={value!r} is outside {allowed}")
    if int(np.min(np.asarray(params.max_steps_in_episode))) < 1:
        raise ValueError("LunarLander max_steps_in_episode must be >= 1")


# --- small vector helpers (Box2D b2Math) ------------------------------------------------------
def _rot(a: jax.Array, x: Any, y: Any) -> tuple[jax.Array, jax.Array]:
    c, s = jnp.cos(a), jnp.sin(a)
    return c * x - s * y, s * x + c * y


def _rot_t(a: jax.Array, x: Any, y: Any) -> tuple[jax.Array, jax.Array]:
    c, s = jnp.cos(a), jnp.sin(a)
    return c * x + s * y, -s * x + c * y


def terrain_from_heights(heights: jax.Array) -> jax.Array:
    """Gymnasium's smooth_y (11,) from the 12 uniform heights (the pad heights are overwritten)."""
    h = jnp.asarray(heights, jnp.float32)
    h = h.at[CHUNKS // 2 - 2 : CHUNKS // 2 + 3].set(np.float32(HELIPAD_Y))
    return np.float32(0.33) * (jnp.roll(h, 1)[:CHUNKS] + h[:CHUNKS] + h[1 : CHUNKS + 1])


def chunk_x() -> np.ndarray:
    """x of the 11 terrain vertices."""
    return np.array([W / (CHUNKS - 1) * i for i in range(CHUNKS)], np.float32)


# --- collision: b2CollideEdgeAndPolygon for a two-sided edge without ghost vertices ---------------
def _pick(onehot: jax.Array, rows: jax.Array) -> jax.Array:
    """rows[index] written as a one-hot sum (no gather under vmap)."""
    return jnp.sum(jnp.where(onehot[:, None], rows, 0.0), axis=0)


def _clip(p0, p1, id0, id1, normal, offset, vertex_index):
    """b2ClipSegmentToLine; returns points (2, 2), ids (2, 4) and the output count."""
    d0 = normal @ p0 - offset
    d1 = normal @ p1 - offset
    interp = d0 / jnp.where(d0 - d1 == 0, 1.0, d0 - d1)
    pi = p0 + interp * (p1 - p0)
    idi = jnp.stack([vertex_index, id0[1], jnp.int32(_VERTEX), jnp.int32(_FACE)])
    keep0, keep1, cross = d0 <= 0, d1 <= 0, d0 * d1 < 0
    first = jnp.where(keep0, p0, jnp.where(keep1, p1, pi))
    first_id = jnp.where(keep0, id0, jnp.where(keep1, id1, idi))
    second = jnp.where(keep0 & keep1, p1, pi)
    second_id = jnp.where(keep0 & keep1, id1, idi)
    count = keep0.astype(jnp.int32) + keep1 + cross
    return jnp.stack([first, second]), jnp.stack([first_id, second_id]), count


def _collide(v1, v2, p, a, verts, normals, centroid):
    """Manifold of a polygon body (origin p, angle a) against the edge v1-v2.

    b2EPCollider::Collide (b2CollideEdge.cpp) for an edge without ghost vertices. Returns
    (count, face_a, local_normal, local_point, local_points (2, 2), keys (2,)) in Box2D's
    conventions: faceA stores the points in the body frame, faceB in the edge (world) frame.
    """
    n = verts.shape[0]
    idx = jnp.arange(n, dtype=jnp.int32)
    radius = np.float32(2.0) * POLYGON_RADIUS
    px, py = _rot(a, verts[:, 0], verts[:, 1])
    pv = jnp.stack([px + p[0], py + p[1]], axis=1)
    pn = jnp.stack(_rot(a, normals[:, 0], normals[:, 1]), axis=1)
    cb = jnp.stack(_rot(a, centroid[0], centroid[1])) + p
    e = v2 - v1
    e = e / jnp.sqrt(e @ e)
    normal1 = jnp.stack([e[1], -e[0]])
    front = normal1 @ (cb - v1) >= 0
    normal = jnp.where(front, normal1, -normal1)
    edge_sep = jnp.min((pv - v1) @ normal)
    s = jnp.minimum(jnp.sum(-pn * (pv - v1), axis=1), jnp.sum(-pn * (pv - v2), axis=1))
    poly_sep = jnp.max(s)
    poly_index = jnp.min(jnp.where(s == poly_sep, idx, n)).astype(jnp.int32)
    separated = (edge_sep > radius) | (poly_sep > radius)
    use_poly = poly_sep > np.float32(0.98) * edge_sep + np.float32(0.001)
    # faceA: reference face on the edge, incident polygon edge the most anti-parallel one.
    dots = pn @ normal
    inc = jnp.min(jnp.where(dots == jnp.min(dots), idx, n)).astype(jnp.int32)
    inc2 = (inc + 1) % n
    ie_a = jnp.stack([_pick(idx == inc, pv), _pick(idx == inc2, pv)])
    zero = jnp.int32(0)
    ids_a = jnp.stack([jnp.stack([zero, inc, jnp.int32(_FACE), zero]),
                       jnp.stack([zero, inc2, jnp.int32(_FACE), zero])])
    # faceB: reference face on the polygon, incident is the edge itself.
    ri2 = (poly_index + 1) % n
    ids_b = jnp.stack([zero, poly_index, zero, jnp.int32(_FACE)])
    ie = jnp.where(use_poly, jnp.stack([v1, v2]), ie_a)
    ids = jnp.where(use_poly, jnp.stack([ids_b, ids_b]), ids_a)
    i1 = jnp.where(use_poly, poly_index, jnp.where(front, 0, 1))
    i2 = jnp.where(use_poly, ri2, jnp.where(front, 1, 0))
    rv1 = jnp.where(use_poly, _pick(idx == poly_index, pv), jnp.where(front, v1, v2))
    rv2 = jnp.where(use_poly, _pick(idx == ri2, pv), jnp.where(front, v2, v1))
    rnormal = jnp.where(use_poly, _pick(idx == poly_index, pn), normal)
    side1 = jnp.stack([rnormal[1], -rnormal[0]])
    c1, c1_ids, n1 = _clip(ie[0], ie[1], ids[0], ids[1], side1, side1 @ rv1, i1)
    c2, c2_ids, n2 = _clip(c1[0], c1[1], c1_ids[0], c1_ids[1], -side1, -side1 @ rv2, i2)
    sep = (c2 - rv1) @ rnormal
    keep = (~separated) & (n1 >= 2) & (n2 >= 2) & (sep <= radius)
    lx, ly = _rot_t(a, c2[:, 0] - p[0], c2[:, 1] - p[1])
    local_pts = jnp.where(use_poly, c2, jnp.stack([lx, ly], axis=1))
    final_ids = jnp.where(use_poly, c2_ids[:, jnp.array([1, 0, 3, 2])], c2_ids)
    keys = final_ids[:, 0] + 256 * final_ids[:, 1] + 65536 * final_ids[:, 2] + 16777216 * final_ids[:, 3]
    # Compact: a rejected first point lets the second take slot 0.
    swap = ~keep[0]
    local_pts = jnp.where(swap, local_pts[::-1], local_pts)
    keys = jnp.where(swap, keys[::-1], keys)
    kept = jnp.where(swap, keep[::-1], keep)
    keys = jnp.where(kept, keys, _ILLEGAL_KEY)
    count = keep.sum().astype(jnp.int32)
    local_normal = jnp.where(use_poly, _pick(idx == poly_index, jnp.asarray(normals)), rnormal)
    local_point = jnp.where(use_poly, _pick(idx == poly_index, jnp.asarray(verts)), rv1)
    return count, ~use_poly, local_normal, local_point, local_pts, keys


def _origin(pos: jax.Array, angle: jax.Array) -> jax.Array:
    """Body origins (b2Body::SynchronizeTransform: p = c - R(a) * localCenter)."""
    ox, oy = _rot(angle, LOCAL_CENTER[:, 0], LOCAL_CENTER[:, 1])
    return pos - jnp.stack([ox, oy], axis=-1)


_MAX_EXTENT = float(max(np.linalg.norm(LANDER_VERTS - LANDER_CENTROID, axis=1).max(),
                        np.linalg.norm(LEG_VERTS, axis=1).max()))


def _candidate_edges(pos: jax.Array) -> jax.Array:
    """(3, 2) indices of the terrain edges a body can touch (-1: none).

    Each body is narrower than an edge (2 m), so its x-range overlaps at most two edges.
    """
    x_lo = jnp.floor((pos[:, 0] - _MAX_EXTENT) / (W / N_EDGES)).astype(jnp.int32)
    k0 = jnp.clip(x_lo, 0, N_EDGES - 1)
    k1 = jnp.where(x_lo + 1 <= N_EDGES - 1, jnp.maximum(x_lo + 1, 1), -1)
    return jnp.stack([k0, k1], axis=1)


def _collide_all(pos, angle, terrain_y, edges):
    """Manifolds of the 3 bodies against their candidate edges (leading axes (3, 2))."""
    xs = jnp.asarray(chunk_x())
    safe = jnp.maximum(edges, 0)
    onehot = safe[..., None] == jnp.arange(N_EDGES)
    x1 = jnp.sum(jnp.where(onehot, xs[:-1], 0.0), axis=-1)
    x2 = jnp.sum(jnp.where(onehot, xs[1:], 0.0), axis=-1)
    y1 = jnp.sum(jnp.where(onehot, terrain_y[:-1], 0.0), axis=-1)
    y2 = jnp.sum(jnp.where(onehot, terrain_y[1:], 0.0), axis=-1)
    v1, v2 = jnp.stack([x1, y1], axis=-1), jnp.stack([x2, y2], axis=-1)
    origin = _origin(pos, angle)
    over_edges = jax.vmap(_collide, in_axes=(0, 0, None, None, None, None, None))
    hull = over_edges(v1[0], v2[0], origin[0], angle[0], LANDER_VERTS, LANDER_NORMALS,
                      LANDER_CENTROID)
    legs = jax.vmap(over_edges, in_axes=(0, 0, 0, 0, None, None, None))(
        v1[1:], v2[1:], origin[1:], angle[1:], LEG_VERTS, LEG_NORMALS, np.zeros(2, np.float32)
    )
    out = jax.tree.map(lambda h, g: jnp.concatenate([h[None], g]), hull, legs)
    count = jnp.where(edges >= 0, out[0], 0)
    return (count, *out[1:])


# The solver below is written with scalars only (vectors are (x, y) tuples): under vmap every
# operation is elementwise over the batch, which lets XLA fuse the 180-iteration loop body.
def _body_origin(cx, cy, a, b):
    ca, sa = jnp.cos(a), jnp.sin(a)
    lx, ly = LOCAL_CENTER[b]
    return cx - (ca * lx - sa * ly), cy - (sa * lx + ca * ly), ca, sa


def _contact_constraint(b, cnt, face_a, ln, lp, lps, c, a):
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
        "b": b, "pcount": cnt, "vcount": jnp.where((cnt == 2) & ~well, 1, cnt),
        "nx": nx, "ny": ny, "r1x": r1x, "r1y": r1y, "r2x": r2x, "r2y": r2y,
        "rn1": rn1, "rn2": rn2, "nm1": jnp.where(k11 > 0, 1.0 / k11, 0.0),
        "nm2": jnp.where(k22 > 0, 1.0 / k22, 0.0), "tm1": jnp.where(kt1 > 0, 1.0 / kt1, 0.0),
        "tm2": jnp.where(kt2 > 0, 1.0 / kt2, 0.0), "k11": k11, "k12": k12, "k22": k22,
        "ki11": inv_det * k22, "ki12": -inv_det * k12, "ki22": inv_det * k11,
        "face_a": face_a, "lnx": ln[0], "lny": ln[1], "lpx": lp[0], "lpy": lp[1],
        "q1x": lps[0, 0], "q1y": lps[0, 1], "q2x": lps[1, 0], "q2y": lps[1, 1],
    }


def _contact_velocity(v, k, ni1, ni2, ti1, ti2):
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


def _contact_position(cx, cy, a, k, j):
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


def _joint_arms(aa, ab, k):
    """World lever arms of joint k: r_A (hull origin - hull centre), r_B (anchor on the leg)."""
    ca, sa = jnp.cos(aa), jnp.sin(aa)
    cb, sb = jnp.cos(ab), jnp.sin(ab)
    lx, ly = -LOCAL_CENTER[0, 0], -LOCAL_CENTER[0, 1]
    bx, by = JOINT_ANCHOR_B[k]
    return ca * lx - sa * ly, sa * lx + ca * ly, cb * bx - sb * by, sb * bx + cb * by


def _joint_constraint(aa, ab, k, limit_state):
    """b2RevoluteJoint::InitVelocityConstraints (K matrix, limit state)."""
    ma, mb, ia, ib = INV_MASS[0], INV_MASS[k + 1], INV_I[0], INV_I[k + 1]
    rax, ray, rbx, rby = _joint_arms(aa, ab, k)
    angle = ab - aa - JOINT_REFERENCE[k]
    state = jnp.where(
        angle <= JOINT_LOWER[k], _AT_LOWER, jnp.where(angle >= JOINT_UPPER[k], _AT_UPPER, _INACTIVE)
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


def _joint_velocity(va, vb, j, k, imp, motor):
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
    limited = state != _INACTIVE
    clamp = ((state == _AT_LOWER) & (iz + fz < 0)) | ((state == _AT_UPPER) & (iz + fz > 0))
    dx = jnp.where(limited, jnp.where(clamp, rx, fx), px_)
    dy = jnp.where(limited, jnp.where(clamp, ry, fy), py_)
    dz = jnp.where(limited, jnp.where(clamp, -iz, fz), 0.0)
    new_imp = (ix + dx, iy + dy, iz + dz)
    vax, vay = vax - ma * dx, vay - ma * dy
    wa = wa - ia * (j["rax"] * dy - j["ray"] * dx + dz)
    vbx, vby = vbx + mb * dx, vby + mb * dy
    wb = wb + ib * (j["rbx"] * dy - j["rby"] * dx + dz)
    return (vax, vay, wa), (vbx, vby, wb), new_imp, new_m


def _joint_position(ca_, aa, cb_, ab, state, k):
    """b2RevoluteJoint::SolvePositionConstraints; returns positions and the converged flag."""
    ma, mb, ia, ib = INV_MASS[0], INV_MASS[k + 1], INV_I[0], INV_I[k + 1]
    angle = ab - aa - JOINT_REFERENCE[k]
    c_low, c_up = angle - JOINT_LOWER[k], angle - JOINT_UPPER[k]
    mm = 1.0 / (ia + ib)
    lim_low = -mm * jnp.clip(c_low + ANGULAR_SLOP, -MAX_ANGULAR_CORRECTION, 0.0)
    lim_up = -mm * jnp.clip(c_up - ANGULAR_SLOP, 0.0, MAX_ANGULAR_CORRECTION)
    lim = jnp.where(state == _AT_LOWER, lim_low, jnp.where(state == _AT_UPPER, lim_up, 0.0))
    ang_err = jnp.where(state == _AT_LOWER, -c_low, jnp.where(state == _AT_UPPER, c_up, 0.0))
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


def _world_step(
    state: EnvState,
    force: jax.Array,
    torque: jax.Array,
    gravity: jax.Array,
    contacts: bool = True,
    velocity_iterations: int = VELOCITY_ITERATIONS,
):
    """One b2World::Step(1/50, 180, 60): collide, solve the island, sleep bookkeeping.

    ``contacts=False`` (static) skips collision entirely; used for the reset step, which
    Gymnasium runs 13 m above the highest possible terrain.
    """
    # -- b2ContactManager::Collide at the start of the step (positions of the last step).
    if contacts:
        edges = _candidate_edges(state.pos)
        count, face_a, lnormal, lpoint, lpts, keys = _collide_all(
            state.pos, state.angle, state.terrain_y, edges
        )
        touching = count > 0
        # Old data of the same (body, edge) pair, then warm-start impulses matched by contact id.
        same = (edges[:, :, None] == state.contact_edge[:, None, :]) & (edges[:, :, None] >= 0)
        old_keys = jnp.where(same[..., None], state.contact_key[:, None], _ILLEGAL_KEY)
        old_ni = jnp.sum(jnp.where(same[..., None], state.normal_impulse[:, None], 0.0), axis=2)
        old_ti = jnp.sum(jnp.where(same[..., None], state.tangent_impulse[:, None], 0.0), axis=2)
        old_keys = jnp.max(old_keys, axis=2)
        match = (keys[..., :, None] == old_keys[..., None, :]) & (keys[..., :, None] != _ILLEGAL_KEY)
        first_match = match & (jnp.cumsum(match, axis=-1) == 1)
        ni0 = jnp.sum(jnp.where(first_match, old_ni[..., None, :], 0.0), axis=-1)
        ti0 = jnp.sum(jnp.where(first_match, old_ti[..., None, :], 0.0), axis=-1)
        valid = jnp.arange(2) < count[..., None]
        ni0, ti0 = jnp.where(valid, ni0, 0.0), jnp.where(valid, ti0, 0.0)
        # Begin/End contact events per (body, edge) pair.
        was = jnp.any(same & state.touching[:, None, :], axis=2)
        still = jnp.any(
            (state.contact_edge[:, :, None] == edges[:, None, :]) & touching[:, None, :], axis=2
        )
        began = touching & ~was
        ended = state.touching & ~still
        game_over = state.game_over | began[0].any()
        leg_begin, leg_end = began[1:].any(axis=1), ended[1:].any(axis=1)
        leg_contact = (state.leg_contact | leg_begin) & ~leg_end
    else:
        edges, touching, keys = state.contact_edge, state.touching, state.contact_key
        ni0, ti0 = state.normal_impulse, state.tangent_impulse
        game_over, leg_contact = state.game_over, state.leg_contact

    # -- Integrate velocities (b2Island::Solve).
    h = DT
    vel = state.vel + h * (jnp.stack([0.0, gravity]) + INV_MASS[:, None] * force)
    omega = state.omega + h * INV_I * torque
    c = [(state.pos[b, 0], state.pos[b, 1]) for b in range(3)]
    a = [state.angle[b] for b in range(3)]
    bv = [(vel[b, 0], vel[b, 1], omega[b]) for b in range(3)]

    # -- Contact constraints of the legs' two candidate edges, warm started.
    cons, cimp = [], []
    for b in CONTACT_BODY_ORDER if contacts else ():
        for e_idx in range(2):
            con = _contact_constraint(
                b, count[b, e_idx], face_a[b, e_idx], lnormal[b, e_idx], lpoint[b, e_idx],
                lpts[b, e_idx], c[b], a[b],
            )
            cons.append((con, e_idx, True))
            n1, n2, t1, t2 = ni0[b, e_idx, 0], ni0[b, e_idx, 1], ti0[b, e_idx, 0], ti0[b, e_idx, 1]
            cimp.append((n1, n2, t1, t2))
            vx, vy, w = bv[b]
            for j, (nj, tj) in enumerate(((n1, t1), (n2, t2))):
                rx, ry = (con["r1x"], con["r1y"]) if j == 0 else (con["r2x"], con["r2y"])
                act = con["vcount"] > j
                pxx = jnp.where(act, nj * con["nx"] + tj * con["ny"], 0.0)
                pyy = jnp.where(act, nj * con["ny"] - tj * con["nx"], 0.0)
                vx, vy = vx + INV_MASS[b] * pxx, vy + INV_MASS[b] * pyy
                w = w + INV_I[b] * (rx * pyy - ry * pxx)
            bv[b] = (vx, vy, w)

    # -- Joint constraints, warm started (dtRatio = 1; everything is zero on the first step).
    joints, jimp, jmot = [], [], []
    for k in range(2):
        j = _joint_constraint(a[0], a[k + 1], k, state.limit_state[k])
        joints.append(j)
        ix, iy = state.joint_impulse[k, 0], state.joint_impulse[k, 1]
        iz = jnp.where(j["changed"] | (j["state"] == _INACTIVE), 0.0, state.joint_impulse[k, 2])
        mot = state.motor_impulse[k]
        jimp.append((ix, iy, iz))
        jmot.append(mot)
        (vax, vay, wa), (vbx, vby, wb) = bv[0], bv[k + 1]
        bv[0] = (vax - INV_MASS[0] * ix, vay - INV_MASS[0] * iy,
                 wa - INV_I[0] * (j["rax"] * iy - j["ray"] * ix + mot + iz))
        bv[k + 1] = (vbx + INV_MASS[k + 1] * ix, vby + INV_MASS[k + 1] * iy,
                     wb + INV_I[k + 1] * (j["rbx"] * iy - j["rby"] * ix + mot + iz))

    # -- Velocity iterations: joints then contacts (b2Island::Solve order).
    def vel_iter(_, carry):
        bv, jimp, jmot, cimp = (list(x) for x in carry)
        for k in JOINT_ORDER:
            bv[0], bv[k + 1], jimp[k], jmot[k] = _joint_velocity(
                bv[0], bv[k + 1], joints[k], k, jimp[k], jmot[k]
            )
        for idx, (con, _, _) in enumerate(cons):
            b = con["b"]
            bv[b], *new = _contact_velocity(bv[b], con, *cimp[idx])
            cimp[idx] = tuple(new)
        return tuple(bv), tuple(jimp), tuple(jmot), tuple(cimp)

    bv, jimp, jmot, cimp = jax.lax.fori_loop(
        0, velocity_iterations, vel_iter, (tuple(bv), tuple(jimp), tuple(jmot), tuple(cimp))
    )

    # -- Store impulses per (body, edge); points beyond the solved count keep their values.
    normal_imp, tangent_imp = ni0, ti0
    for (con, e_idx, _), (n1, n2, t1, t2) in zip(cons, cimp, strict=True):
        b = con["b"]
        two = con["vcount"] == 2
        new_n = jnp.stack([n1, jnp.where(two, n2, normal_imp[b, e_idx, 1])])
        new_t = jnp.stack([t1, jnp.where(two, t2, tangent_imp[b, e_idx, 1])])
        normal_imp = normal_imp.at[b, e_idx].set(new_n)
        tangent_imp = tangent_imp.at[b, e_idx].set(new_t)

    # -- Integrate positions with the translation/rotation clamps.
    vel = jnp.stack([jnp.stack(v[:2]) for v in bv])
    omega = jnp.stack([v[2] for v in bv])
    trans2 = jnp.sum((h * vel) ** 2, axis=1)
    vel = vel * jnp.where(trans2 > MAX_TRANSLATION**2, MAX_TRANSLATION / jnp.sqrt(trans2), 1.0)[:, None]
    rot = h * omega
    omega = omega * jnp.where(rot * rot > MAX_ROTATION**2, MAX_ROTATION / jnp.abs(rot), 1.0)
    c = [(c[b][0] + h * vel[b, 0], c[b][1] + h * vel[b, 1]) for b in range(3)]
    a = [a[b] + h * omega[b] for b in range(3)]

    # -- Position iterations, stopping like Box2D once contacts and joints are within slop.
    def pos_cond(carry):
        i, _, _, done = carry
        return (i < POSITION_ITERATIONS) & ~done

    def pos_iter(carry):
        i, cs, as_, _ = carry
        cs, as_ = list(cs), list(as_)
        min_sep = jnp.float32(0.0)
        for con, _, _ in cons:
            b = con["b"]
            for j in range(2):
                cx, cy, as_[b], sep = _contact_position(cs[b][0], cs[b][1], as_[b], con, j)
                cs[b] = (cx, cy)
                min_sep = jnp.minimum(min_sep, sep)
        ok = min_sep >= -3.0 * LINEAR_SLOP
        for k in JOINT_ORDER:
            cs[0], as_[0], cs[k + 1], as_[k + 1], jok = _joint_position(
                cs[0], as_[0], cs[k + 1], as_[k + 1], joints[k]["state"], k
            )
            ok = ok & jok
        return i + 1, tuple(cs), tuple(as_), ok

    _, cs, as_, solved = jax.lax.while_loop(
        pos_cond, pos_iter, (jnp.int32(0), tuple(c), tuple(a), jnp.bool_(False))
    )

    # -- Sleep (b2Island::Solve with allowSleep).
    resting = (omega * omega <= ANGULAR_SLEEP_TOL**2) & (
        jnp.sum(vel * vel, axis=1) <= LINEAR_SLEEP_TOL**2
    )
    sleep_time = jnp.where(resting, state.sleep_time + h, 0.0)
    asleep = (jnp.min(sleep_time) >= TIME_TO_SLEEP) & solved
    return state.replace(
        pos=jnp.stack([jnp.stack(p) for p in cs]),
        angle=jnp.stack(as_),
        vel=vel,
        omega=omega,
        joint_impulse=jnp.stack([jnp.stack(x) for x in jimp]),
        motor_impulse=jnp.stack(jmot),
        limit_state=jnp.stack([j["state"] for j in joints]).astype(jnp.int32),
        sleep_time=sleep_time,
        contact_edge=edges,
        touching=touching,
        contact_key=keys,
        normal_impulse=normal_imp,
        tangent_impulse=tangent_imp,
        leg_contact=leg_contact,
        game_over=game_over,
        awake=~asleep,
    )


# --- game logic (Gymnasium LunarLander.step) ------------------------------------------------------
def decode_action(action: jax.Array, continuous: bool) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(m_power, s_power, direction) exactly as Gymnasium decodes discrete/continuous actions."""
    if continuous:
        act = jnp.clip(jnp.asarray(action, jnp.float32), -1.0, 1.0)
        m_power = jnp.where(act[0] > 0, (jnp.clip(act[0], 0.0, 1.0) + 1.0) * 0.5, 0.0)
        side = jnp.abs(act[1]) > 0.5
        s_power = jnp.where(side, jnp.clip(jnp.abs(act[1]), 0.5, 1.0), 0.0)
        direction = jnp.where(side, jnp.sign(act[1]), 0.0)
    else:
        act = jnp.asarray(action, jnp.int32)
        m_power = jnp.where(act == 2, 1.0, 0.0)
        side = (act == 1) | (act == 3)
        s_power = jnp.where(side, 1.0, 0.0)
        direction = jnp.where(side, act - 2, 0).astype(jnp.float32)
    return m_power.astype(jnp.float32), s_power.astype(jnp.float32), direction


def _engine_impulses(state: EnvState, m_power, s_power, direction, dispersion):
    """Apply Gymnasium's main/side engine impulses to the hull (b2Body::ApplyLinearImpulse)."""
    pos = _origin(state.pos, state.angle)[0]
    ang = state.angle[0]
    tip = jnp.stack([jnp.sin(ang), jnp.cos(ang)])
    side = jnp.stack([-tip[1], tip[0]])
    d = jnp.asarray(dispersion, jnp.float32) / SCALE
    # Main engine.
    off = MAIN_ENGINE_Y_LOCATION / SCALE + 2 * d[0]
    mx = tip[0] * off + side[0] * d[1]
    my = -tip[1] * off - side[1] * d[1]
    main_point = pos + jnp.stack([mx, my])
    main_imp = jnp.stack([-mx, -my]) * MAIN_ENGINE_POWER * m_power
    # Side engines (the 17-vs-SIDE_ENGINE_HEIGHT quirk is Gymnasium's).
    lat = 3 * d[1] + direction * SIDE_ENGINE_AWAY / SCALE
    sx = tip[0] * d[0] + side[0] * lat
    sy = -tip[1] * d[0] - side[1] * lat
    side_point = pos + jnp.stack([sx - tip[0] * 17 / SCALE, sy + tip[1] * SIDE_ENGINE_HEIGHT / SCALE])
    side_imp = jnp.stack([-sx, -sy]) * SIDE_ENGINE_POWER * s_power
    vel, omega = state.vel, state.omega
    for point, imp in ((main_point, main_imp), (side_point, side_imp)):
        r = point - state.pos[0]
        vel = vel.at[0].add(INV_MASS[0] * imp)
        omega = omega.at[0].add(INV_I[0] * (r[0] * imp[1] - r[1] * imp[0]))
    return state.replace(vel=vel, omega=omega)


def observation(state: EnvState) -> jax.Array:
    """Gymnasium's 8-dim observation."""
    pos = _origin(state.pos, state.angle)[0]
    vel = state.vel[0]
    return jnp.stack(
        [
            (pos[0] - W / 2) / (W / 2),
            (pos[1] - (HELIPAD_Y + LEG_DOWN / SCALE)) / (H / 2),
            vel[0] * (W / 2) / FPS,
            vel[1] * (H / 2) / FPS,
            state.angle[0],
            20.0 * state.omega[0] / FPS,
            state.leg_contact[0].astype(jnp.float32),
            state.leg_contact[1].astype(jnp.float32),
        ]
    ).astype(jnp.float32)


def shaping(obs: jax.Array) -> jax.Array:
    """Gymnasium's potential: distance, speed, tilt and leg-contact terms."""
    return (
        -100 * jnp.sqrt(obs[0] ** 2 + obs[1] ** 2)
        - 100 * jnp.sqrt(obs[2] ** 2 + obs[3] ** 2)
        - 100 * jnp.abs(obs[4])
        + 10 * obs[6]
        + 10 * obs[7]
    )


def reward_and_termination(
    obs: jax.Array, prev_shaping: jax.Array, m_power, s_power, game_over, awake
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(reward, terminated, shaping) with Gymnasium's -100 crash / +100 sleep overrides."""
    shp = shaping(obs)
    reward = shp - prev_shaping - m_power * 0.30 - s_power * 0.03
    crashed = game_over | (jnp.abs(obs[0]) >= 1.0)
    reward = jnp.where(crashed, -100.0, reward)
    reward = jnp.where(~awake, 100.0, reward)
    return reward.astype(jnp.float32), crashed | ~awake, shp


def _wind(state: EnvState, params: EnvParams):
    on = jnp.asarray(params.enable_wind) & ~(state.leg_contact[0] | state.leg_contact[1])

    def mag(idx):
        idx = idx.astype(jnp.float32)
        return jnp.tanh(jnp.sin(0.02 * idx) + jnp.sin(np.float32(math.pi * 0.01) * idx))

    force = jnp.where(on, mag(state.wind_idx) * params.wind_power, 0.0)
    torque = jnp.where(on, mag(state.torque_idx) * params.turbulence_power, 0.0)
    state = state.replace(wind_idx=state.wind_idx + on, torque_idx=state.torque_idx + on)
    return state, force, torque


def _physics_step(
    state, m_power, s_power, direction, dispersion, extra_force, params, contacts=True,
    velocity_iterations=VELOCITY_ITERATIONS,
):
    state, wind_f, wind_t = _wind(state, params)
    state = _engine_impulses(state, m_power, s_power, direction, dispersion)
    force = jnp.zeros((3, 2), jnp.float32).at[0].set(extra_force + jnp.stack([wind_f, 0.0]))
    torque = jnp.zeros(3, jnp.float32).at[0].set(wind_t)
    gravity = jnp.asarray(params.gravity, jnp.float32)
    return _world_step(state, force, torque, gravity, contacts, velocity_iterations)


def initial_state(heights: jax.Array, wind_offsets: jax.Array | None = None) -> EnvState:
    """World right after Gymnasium's reset() built it (before the reset step)."""
    x0, y0 = np.float32(W / 2), np.float32(H)
    origins = np.array(
        [[x0, y0]] + [[W / 2 - i * LEG_AWAY / SCALE, H] for i in LEG_SIGN], np.float32
    )
    angle = np.array([0.0] + [i * 0.05 for i in LEG_SIGN], np.float32)
    wind = jnp.zeros(2, jnp.int32) if wind_offsets is None else jnp.asarray(wind_offsets, jnp.int32)
    return EnvState(
        pos=jnp.asarray(origins + LOCAL_CENTER),
        angle=jnp.asarray(angle),
        vel=jnp.zeros((3, 2), jnp.float32),
        omega=jnp.zeros(3, jnp.float32),
        joint_impulse=jnp.zeros((2, 3), jnp.float32),
        motor_impulse=jnp.zeros(2, jnp.float32),
        limit_state=jnp.zeros(2, jnp.int32),
        sleep_time=jnp.zeros(3, jnp.float32),
        contact_edge=jnp.full((3, 2), -1, jnp.int32),
        touching=jnp.zeros((3, 2), bool),
        contact_key=jnp.full((3, 2, 2), _ILLEGAL_KEY, jnp.int32),
        normal_impulse=jnp.zeros((3, 2, 2), jnp.float32),
        tangent_impulse=jnp.zeros((3, 2, 2), jnp.float32),
        leg_contact=jnp.zeros(2, bool),
        game_over=jnp.bool_(False),
        awake=jnp.bool_(True),
        terrain_y=terrain_from_heights(heights),
        prev_shaping=jnp.float32(0.0),
        wind_idx=wind[0],
        torque_idx=wind[1],
        time=0,
    )


def reset_from_draws(
    heights: jax.Array,
    init_force: jax.Array,
    params: EnvParams,
    wind_offsets: jax.Array | None = None,
    velocity_iterations: int = VELOCITY_ITERATIONS,
) -> tuple[jax.Array, EnvState]:
    """Gymnasium's reset given its draws: 12 heights ~U(0, H/2), force ~U(+-1000)^2, and (wind
    only) two integers in [-9999, 9999). Runs the reset step (nop action) like Gymnasium."""
    state = initial_state(heights, wind_offsets)
    zero = jnp.float32(0.0)
    state = _physics_step(
        state, zero, zero, zero, jnp.zeros(2, jnp.float32), jnp.asarray(init_force, jnp.float32),
        params, contacts=False, velocity_iterations=velocity_iterations,
    )
    obs = observation(state)
    return obs, state.replace(prev_shaping=shaping(obs), time=0)


def step_from_draws(
    state: EnvState,
    action: jax.Array,
    dispersion: jax.Array,
    params: EnvParams,
    continuous: bool = False,
    velocity_iterations: int = VELOCITY_ITERATIONS,
) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, dict[str, jax.Array]]:
    """Gymnasium's step given the two per-step U(-1, 1) dispersion draws."""
    m_power, s_power, direction = decode_action(action, continuous)
    state = _physics_step(
        state, m_power, s_power, direction, dispersion, jnp.zeros(2, jnp.float32), params,
        velocity_iterations=velocity_iterations,
    )
    obs = observation(state)
    reward, terminated, shp = reward_and_termination(
        obs, state.prev_shaping, m_power, s_power, state.game_over, state.awake
    )
    state = state.replace(prev_shaping=shp, time=state.time + 1)
    info = {"landed": ~state.awake, "crashed": terminated & state.awake}
    return obs, state, reward, terminated, info


class LunarLander(environment.Environment[EnvState, EnvParams]):
    """LunarLander-v3 (discrete, or continuous with ``continuous=True``) in pure JAX.

    ``velocity_iterations`` (static) defaults to Box2D's 180 as Gymnasium calls it; fewer
    iterations run faster and deviate from Box2D by the amounts in docs/lunar_lander.md.
    """

    def __init__(self, continuous: bool = False, velocity_iterations: int = VELOCITY_ITERATIONS):
        super().__init__()
        if int(velocity_iterations) < 1:
            raise ValueError(f"velocity_iterations must be >= 1, got {velocity_iterations}")
        self.continuous = bool(continuous)
        self.velocity_iterations = int(velocity_iterations)
        self.obs_shape = (8,)

    @property
    def default_params(self) -> EnvParams:
        return EnvParams()

    @property
    def name(self) -> str:
        return "LunarLander-v3"

    @property
    def num_actions(self) -> int:
        return 2 if self.continuous else 4

    def step_env(
        self, key: jax.Array, state: EnvState, action: int | float | jax.Array, params: EnvParams
    ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, dict[Any, Any]]:
        dispersion = jax.random.uniform(key, (2,), jnp.float32, -1.0, 1.0)
        obs, state, reward, terminated, info = step_from_draws(
            state, action, dispersion, params, self.continuous, self.velocity_iterations
        )
        info = {**info, "discount": 1.0 - terminated.astype(jnp.float32)}
        return obs, state, reward, terminated, info

    def reset_env(self, key: jax.Array, params: EnvParams) -> tuple[jax.Array, EnvState]:
        k_h, k_f, k_w = jax.random.split(key, 3)
        heights = jax.random.uniform(k_h, (CHUNKS + 1,), jnp.float32, 0.0, H / 2)
        force = jax.random.uniform(k_f, (2,), jnp.float32, -INITIAL_RANDOM, INITIAL_RANDOM)
        wind = jax.random.randint(k_w, (2,), -9999, 9999)
        return reset_from_draws(heights, force, params, wind, self.velocity_iterations)

    def get_obs(self, state: EnvState, params: EnvParams | None = None, key: Any = None) -> jax.Array:
        return observation(state)

    def is_terminated(self, state: EnvState, params: EnvParams) -> jax.Array:
        obs = observation(state)
        return state.game_over | (jnp.abs(obs[0]) >= 1.0) | ~state.awake

    def action_space(self, params: EnvParams | None = None) -> spaces.Discrete | spaces.Box:
        if self.continuous:
            return spaces.Box(-1.0, 1.0, (2,), jnp.float32)
        return spaces.Discrete(4)

    def observation_space(self, params: EnvParams | None = None) -> spaces.Box:
        return spaces.Box(jnp.asarray(OBS_LOW), jnp.asarray(OBS_HIGH), (8,), jnp.float32)


def heuristic_action(obs: jax.Array, continuous: bool = False) -> jax.Array:
    """Gymnasium's ``heuristic()`` demo controller, ported to JAX (one observation)."""
    angle_targ = jnp.clip(obs[0] * 0.5 + obs[2] * 1.0, -0.4, 0.4)
    hover_targ = 0.55 * jnp.abs(obs[0])
    angle_todo = (angle_targ - obs[4]) * 0.5 - obs[5] * 1.0
    hover_todo = (hover_targ - obs[1]) * 0.5 - obs[3] * 0.5
    legs = (obs[6] != 0) | (obs[7] != 0)
    angle_todo = jnp.where(legs, 0.0, angle_todo)
    hover_todo = jnp.where(legs, -obs[3] * 0.5, hover_todo)
    if continuous:
        return jnp.clip(jnp.stack([hover_todo * 20 - 1, -angle_todo * 20]), -1.0, 1.0)
    return jnp.where(
        (hover_todo > jnp.abs(angle_todo)) & (hover_todo > 0.05),
        2,
        jnp.where(angle_todo < -0.05, 3, jnp.where(angle_todo > 0.05, 1, 0)),
    ).astype(jnp.int32)


def load_gymnasium_lunar_lander() -> ModuleType:
    """Gymnasium's lunar_lander module (reference for tests/benchmarks; needs ``box2d``).

    Loaded from its file so that Gymnasium's box2d package ``__init__`` (which imports the
    pygame-dependent CarRacing) is not required.
    """
    import gymnasium

    path = os.path.join(os.path.dirname(gymnasium.__file__), "envs", "box2d", "lunar_lander.py")
    spec = importlib.util.spec_from_file_location("_gymnasium_lunar_lander", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class DrawRecorder:
    """Stands in for Gymnasium's ``np_random`` and logs every draw (for replaying in JAX)."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.draws: list[np.ndarray] = []

    def uniform(self, *args: Any, **kwargs: Any) -> Any:
        value = self.rng.uniform(*args, **kwargs)
        self.draws.append(np.atleast_1d(value).astype(np.float64))
        return value

    def integers(self, *args: Any, **kwargs: Any) -> Any:
        value = self.rng.integers(*args, **kwargs)
        self.draws.append(np.atleast_1d(value))
        return value


def free_flight_replay(
    seed: int,
    max_steps: int = 1000,
    continuous: bool = False,
    velocity_iterations: int = VELOCITY_ITERATIONS,
) -> dict[str, np.ndarray]:
    """Step Gymnasium and the port side by side on Gymnasium's recorded draws, random actions.

    Stops before Gymnasium's first ground contact (a leg flag or game_over) or termination.
    Returns per-step absolute observation and reward differences (needs ``box2d``).
    """
    module = load_gymnasium_lunar_lander()
    genv = module.LunarLander(continuous=continuous)
    recorder = DrawRecorder(np.random.default_rng(seed))
    genv.np_random = recorder
    genv.action_space.seed(seed)
    obs_g, _ = genv.reset()
    params = EnvParams()
    obs_j, state = _jit_reset(
        recorder.draws[0], np.concatenate(recorder.draws[1:3]), params,
        velocity_iterations=velocity_iterations,
    )
    obs_diff, rew_diff = [np.abs(np.asarray(obs_j) - obs_g).max()], []
    for _ in range(max_steps):
        action = genv.action_space.sample()
        n_draws = len(recorder.draws)
        obs_g, rew_g, term, _, _ = genv.step(action)
        if obs_g[6] or obs_g[7] or genv.game_over or term:
            break
        dispersion = np.concatenate(recorder.draws[n_draws : n_draws + 2])
        obs_j, state, rew_j, _, _ = _jit_step(
            state, action, dispersion, params, continuous, velocity_iterations
        )
        obs_diff.append(np.abs(np.asarray(obs_j) - obs_g).max())
        rew_diff.append(abs(float(rew_j) - rew_g))
    genv.close()
    return {"obs_diff": np.asarray(obs_diff), "reward_diff": np.asarray(rew_diff)}


_jit_reset = jax.jit(reset_from_draws, static_argnames="velocity_iterations")
_jit_step = jax.jit(step_from_draws, static_argnames=("continuous", "velocity_iterations"))
