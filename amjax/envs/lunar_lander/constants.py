"""Constants of Gymnasium's ``lunar_lander.py`` (v1.3.0) and Box2D 2.3's ``b2Settings.h``; mass properties
computed from the shapes as ``b2PolygonShape::ComputeMass`` does."""

from __future__ import annotations

import math

import numpy as np

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
FEATURE_VERTEX, FEATURE_FACE = 0, 1
ILLEGAL_KEY = -1

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
LEG_VERTS = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float32) * np.array(
    [LEG_W / SCALE, LEG_H / SCALE], np.float32
)  # b2PolygonShape::SetAsBox order
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
LIMIT_INACTIVE, LIMIT_AT_LOWER, LIMIT_AT_UPPER = 0, 1, 2

OBS_LOW = np.array([-2.5, -2.5, -10.0, -10.0, -2 * math.pi, -10.0, -0.0, -0.0], np.float32)
OBS_HIGH = np.array([2.5, 2.5, 10.0, 10.0, 2 * math.pi, 10.0, 1.0, 1.0], np.float32)
