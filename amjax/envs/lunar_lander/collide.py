"""Terrain and contact manifolds: ``b2CollideEdgeAndPolygon`` for two-sided edges without ghost vertices."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from amjax.envs.lunar_lander.constants import (
    CHUNKS,
    FEATURE_FACE,
    FEATURE_VERTEX,
    HELIPAD_Y,
    ILLEGAL_KEY,
    LANDER_CENTROID,
    LANDER_NORMALS,
    LANDER_VERTS,
    LEG_NORMALS,
    LEG_VERTS,
    LOCAL_CENTER,
    N_EDGES,
    POLYGON_RADIUS,
    W,
)
from amjax.envs.lunar_lander.fusion import materialized

# --- small vector helpers (Box2D b2Math) ------------------------------------------------------
# sin and cos in float32 from multiplies and adds only, so that XLA vectorises them inside the solver's loops (its
# sin and cos are scalar library calls there, a quarter of a step's time). Cody-Waite reduction by pi/2 with pi/2
# split in three parts, then minimax polynomials on [-pi/4, pi/4]: the constants are Cephes' sinf.c / cosf.c
# (S. Moshier), scaled from pi/4 to pi/2. Within about 1 ulp of the library's sinf / cosf for |a| < 1e4.
_PIO2 = tuple(np.float32(x) for x in (1.5703125, 4.837512969970703125e-4, 7.54978995489188216e-8))
_TWO_OVER_PI = np.float32(0.636619772367581343)
_SIN = tuple(np.float32(x) for x in (-1.9515295891e-4, 8.3321608736e-3, -1.6666654611e-1))
_COS = tuple(np.float32(x) for x in (2.443315711809948e-5, -1.388731625493765e-3, 4.166664568298827e-2))


def sin_cos(a: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(sin a, cos a) of float32 ``a`` (Box2D's b2Rot::Set)."""
    # Materialised: each consumer kernel reads the pair instead of recomputing the polynomial.
    return materialized(_sin_cos_polynomial, jnp.asarray(a, jnp.float32))


def _sin_cos_polynomial(a: jax.Array) -> tuple[jax.Array, jax.Array]:
    q = jnp.round(a * _TWO_OVER_PI)
    y = ((a - q * _PIO2[0]) - q * _PIO2[1]) - q * _PIO2[2]
    z = y * y
    sin_y = y + y * z * ((_SIN[0] * z + _SIN[1]) * z + _SIN[2])
    cos_y = np.float32(1.0) - np.float32(0.5) * z + z * z * ((_COS[0] * z + _COS[1]) * z + _COS[2])
    quadrant = q.astype(jnp.int32) & 3
    sin_a = jnp.where(quadrant == 0, sin_y, jnp.where(quadrant == 1, cos_y, jnp.where(quadrant == 2, -sin_y, -cos_y)))
    cos_a = jnp.where(quadrant == 0, cos_y, jnp.where(quadrant == 1, -sin_y, jnp.where(quadrant == 2, -cos_y, sin_y)))
    return sin_a, cos_a


def rot(a: jax.Array, x: Any, y: Any) -> tuple[jax.Array, jax.Array]:
    s, c = sin_cos(a)
    return c * x - s * y, s * x + c * y


def rot_t(a: jax.Array, x: Any, y: Any) -> tuple[jax.Array, jax.Array]:
    s, c = sin_cos(a)
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
    idi = jnp.stack([vertex_index, id0[1], jnp.int32(FEATURE_VERTEX), jnp.int32(FEATURE_FACE)])
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
    px, py = rot(a, verts[:, 0], verts[:, 1])
    pv = jnp.stack([px + p[0], py + p[1]], axis=1)
    pn = jnp.stack(rot(a, normals[:, 0], normals[:, 1]), axis=1)
    cb = jnp.stack(rot(a, centroid[0], centroid[1])) + p
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
    ids_a = jnp.stack(
        [jnp.stack([zero, inc, jnp.int32(FEATURE_FACE), zero]), jnp.stack([zero, inc2, jnp.int32(FEATURE_FACE), zero])]
    )
    # faceB: reference face on the polygon, incident is the edge itself.
    ri2 = (poly_index + 1) % n
    ids_b = jnp.stack([zero, poly_index, zero, jnp.int32(FEATURE_FACE)])
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
    lx, ly = rot_t(a, c2[:, 0] - p[0], c2[:, 1] - p[1])
    local_pts = jnp.where(use_poly, c2, jnp.stack([lx, ly], axis=1))
    final_ids = jnp.where(use_poly, c2_ids[:, jnp.array([1, 0, 3, 2])], c2_ids)
    keys = final_ids[:, 0] + 256 * final_ids[:, 1] + 65536 * final_ids[:, 2] + 16777216 * final_ids[:, 3]
    # Compact: a rejected first point lets the second take slot 0.
    swap = ~keep[0]
    local_pts = jnp.where(swap, local_pts[::-1], local_pts)
    keys = jnp.where(swap, keys[::-1], keys)
    kept = jnp.where(swap, keep[::-1], keep)
    keys = jnp.where(kept, keys, ILLEGAL_KEY)
    count = keep.sum().astype(jnp.int32)
    local_normal = jnp.where(use_poly, _pick(idx == poly_index, jnp.asarray(normals)), rnormal)
    local_point = jnp.where(use_poly, _pick(idx == poly_index, jnp.asarray(verts)), rv1)
    return count, ~use_poly, local_normal, local_point, local_pts, keys


def body_origins(pos: jax.Array, angle: jax.Array) -> jax.Array:
    """Body origins (b2Body::SynchronizeTransform: p = c - R(a) * localCenter)."""
    ox, oy = rot(angle, LOCAL_CENTER[:, 0], LOCAL_CENTER[:, 1])
    return pos - jnp.stack([ox, oy], axis=-1)


_MAX_EXTENT = float(
    max(np.linalg.norm(LANDER_VERTS - LANDER_CENTROID, axis=1).max(), np.linalg.norm(LEG_VERTS, axis=1).max())
)


def candidate_edges(pos: jax.Array) -> jax.Array:
    """(3, 2) indices of the terrain edges a body can touch (-1: none).

    Each body is narrower than an edge (2 m), so its x-range overlaps at most two edges.
    """
    x_lo = jnp.floor((pos[:, 0] - _MAX_EXTENT) / (W / N_EDGES)).astype(jnp.int32)
    k0 = jnp.clip(x_lo, 0, N_EDGES - 1)
    k1 = jnp.where(x_lo + 1 <= N_EDGES - 1, jnp.maximum(x_lo + 1, 1), -1)
    return jnp.stack([k0, k1], axis=1)


def collide_all(pos, angle, terrain_y, edges):
    """Manifolds of the 3 bodies against their candidate edges (leading axes (3, 2))."""
    xs = jnp.asarray(chunk_x())
    safe = jnp.maximum(edges, 0)
    onehot = safe[..., None] == jnp.arange(N_EDGES)
    x1 = jnp.sum(jnp.where(onehot, xs[:-1], 0.0), axis=-1)
    x2 = jnp.sum(jnp.where(onehot, xs[1:], 0.0), axis=-1)
    y1 = jnp.sum(jnp.where(onehot, terrain_y[:-1], 0.0), axis=-1)
    y2 = jnp.sum(jnp.where(onehot, terrain_y[1:], 0.0), axis=-1)
    v1, v2 = jnp.stack([x1, y1], axis=-1), jnp.stack([x2, y2], axis=-1)
    origin = body_origins(pos, angle)
    over_edges = jax.vmap(_collide, in_axes=(0, 0, None, None, None, None, None))
    hull = over_edges(v1[0], v2[0], origin[0], angle[0], LANDER_VERTS, LANDER_NORMALS, LANDER_CENTROID)
    legs = jax.vmap(over_edges, in_axes=(0, 0, 0, 0, None, None, None))(
        v1[1:], v2[1:], origin[1:], angle[1:], LEG_VERTS, LEG_NORMALS, np.zeros(2, np.float32)
    )
    out = jax.tree.map(lambda h, g: jnp.concatenate([h[None], g]), hull, legs)
    count = jnp.where(edges >= 0, out[0], 0)
    return (count, *out[1:])
