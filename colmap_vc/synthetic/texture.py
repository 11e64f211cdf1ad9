"""Procedural solid textures, evaluated at 3D points (no UV maps needed).

Surfaces are coloured from coordinates that move with them: world coordinates for the
static backdrop, rest-pose template coordinates for the people (so a shirt's stripes
follow the body). Everything is vectorized over points and seeded by a
:class:`TextureSeed` so a scene renders identically from its seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..structs import FloatArray, IndexArray


@dataclass(frozen=True, slots=True)
class TextureSeed:
    """Random tables behind the value noise of one scene."""

    perm: IndexArray  # (512,) int64, a doubled permutation of 0..255
    values: FloatArray  # (256,) float64 in [0, 1)

    @classmethod
    def from_rng(cls, rng: np.random.Generator) -> TextureSeed:
        """Draw the tables from ``rng``."""
        p = rng.permutation(256).astype(np.int64)
        return cls(np.concatenate([p, p]), rng.random(256))


def _hash(
    seed: TextureSeed, ix: IndexArray, iy: IndexArray, iz: IndexArray
) -> FloatArray:
    p = seed.perm
    return seed.values[p[p[p[ix & 255] + (iy & 255)] + (iz & 255)]]


def value_noise(seed: TextureSeed, points: FloatArray) -> FloatArray:
    """Smooth value noise in [0, 1] at points (N, 3), one lattice cell per unit."""
    cell = np.floor(points)
    f = points - cell
    w = f * f * (3.0 - 2.0 * f)  # smoothstep weights
    i = cell.astype(np.int64)
    out = np.zeros(len(points))
    for dx in (0, 1):  # 8 lattice corners, each vectorized over all points
        wx = w[:, 0] if dx else 1.0 - w[:, 0]
        for dy in (0, 1):
            wy = w[:, 1] if dy else 1.0 - w[:, 1]
            for dz in (0, 1):
                wz = w[:, 2] if dz else 1.0 - w[:, 2]
                out += (
                    wx * wy * wz * _hash(seed, i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz)
                )
    return out


def fbm(
    seed: TextureSeed, points: FloatArray, base_freq: float, octaves: int = 4
) -> FloatArray:
    """Fractal sum of value noise in about [0, 1] (gain 0.5, lacunarity 2.03)."""
    total = np.zeros(len(points))
    amp, norm, freq = 1.0, 0.0, base_freq
    for k in range(octaves):
        # Offsetting each octave decorrelates lattice corners across octaves.
        total += amp * value_noise(seed, points * freq + 17.31 * k)
        norm += amp
        amp *= 0.5
        freq *= 2.03
    return total / norm


def disk_field(
    seed: TextureSeed, uv: FloatArray, cell_m: float
) -> tuple[FloatArray, FloatArray]:
    """Random disks on a jittered 2D grid: the blob texture SIFT detects well.

    Args:
        seed: noise tables.
        uv: (N, 2) surface coordinates in metres.
        cell_m: grid cell size (disk radii are 15-45% of it).

    Returns:
        inside (N,) float64 in [0, 1] (1 inside a disk, anti-aliased edge) and the
        disk's random value (N,) in [0, 1) used to pick its colour.
    """
    g = uv / cell_m
    cell = np.floor(g).astype(np.int64)
    inside = np.zeros(len(uv))
    value = np.zeros(len(uv))
    for dx in (-1, 0, 1):  # a disk may reach into the neighbouring cells
        for dy in (-1, 0, 1):
            cx, cy = cell[:, 0] + dx, cell[:, 1] + dy
            zero = np.zeros_like(cx)
            jx = _hash(seed, cx, cy, zero)
            jy = _hash(seed, cx, cy, zero + 1)
            r = 0.15 + 0.3 * _hash(seed, cx, cy, zero + 2)
            d = np.hypot(g[:, 0] - (cx + jx), g[:, 1] - (cy + jy))
            cover = np.clip((r - d) * 20.0, 0.0, 1.0)
            better = cover > inside
            inside = np.where(better, cover, inside)
            value = np.where(better, _hash(seed, cx, cy, zero + 3), value)
    return inside, value


def palette(value: FloatArray, colours: FloatArray) -> FloatArray:
    """Map values in [0, 1] to RGB (N, 3), linearly interpolating ``colours`` (K, 3)."""
    x = np.clip(value, 0.0, 1.0) * (len(colours) - 1)
    i = np.minimum(np.floor(x).astype(np.int64), len(colours) - 2)
    t = (x - i)[:, None]
    return (1.0 - t) * colours[i] + t * colours[i + 1]


_ROOM_COLOURS = np.array(
    [
        [0.85, 0.78, 0.62],
        [0.55, 0.35, 0.22],
        [0.20, 0.35, 0.55],
        [0.75, 0.25, 0.20],
        [0.30, 0.55, 0.30],
        [0.95, 0.90, 0.80],
        [0.15, 0.15, 0.18],
    ]
)


def room_surface(
    seed: TextureSeed, points: FloatArray, normals: FloatArray
) -> FloatArray:
    """A richly textured room: wood-like floor, walls with blob posters. (N, 3) RGB."""
    n = np.abs(normals)
    is_floor = n[:, 2] > 0.5
    # Planar coordinates of each wall or floor point (drop the normal's axis).
    uv = np.where(
        is_floor[:, None],
        points[:, [0, 1]],
        np.where((n[:, 0] > n[:, 1])[:, None], points[:, [1, 2]], points[:, [0, 2]]),
    )
    grain = fbm(seed, points, base_freq=3.0, octaves=5)
    inside, value = disk_field(seed, uv, cell_m=0.35)
    base = palette(grain, _ROOM_COLOURS[[0, 1, 5]])
    blobs = palette(value, _ROOM_COLOURS)
    big_inside, big_value = disk_field(seed, uv + 31.7, cell_m=1.2)
    out = (1 - inside[:, None]) * base + inside[:, None] * blobs
    out = (1 - 0.6 * big_inside[:, None]) * out + 0.6 * big_inside[:, None] * palette(
        big_value, _ROOM_COLOURS[::-1]
    )
    return np.clip(out, 0.0, 1.0)


def dome_surface(
    seed: TextureSeed, points: FloatArray, bary: FloatArray, face_idx: IndexArray
) -> FloatArray:
    """Panoptic-like geodesic panels: near-uniform light grey, darker seams. (N, 3)."""
    zeros = np.zeros_like(face_idx)
    shade = 0.78 + 0.05 * _hash(seed, face_idx, zeros, zeros + 5)
    seam = np.clip(bary.min(axis=1) / 0.02, 0.0, 1.0)  # 0 on a panel edge
    tone = shade * (0.75 + 0.25 * seam) + 0.02 * fbm(seed, points, 2.0, 2)
    return np.repeat(tone[:, None], 3, axis=1) * np.array([1.0, 1.0, 0.97])


def dome_floor(seed: TextureSeed, points: FloatArray) -> FloatArray:
    """A dark, faintly mottled floor (little for SIFT to hold on to). (N, 3)."""
    tone = 0.30 + 0.05 * fbm(seed, points, 1.5, 3)
    return np.repeat(tone[:, None], 3, axis=1) * np.array([1.0, 0.97, 0.93])


@dataclass(frozen=True, kw_only=True, slots=True)
class Outfit:
    """Colours and pattern of one person's clothes."""

    skin: FloatArray  # (3,)
    hair: FloatArray  # (3,)
    shirt: FloatArray  # (2, 3) two colours of the pattern
    trousers: FloatArray  # (3,)
    shoes: FloatArray  # (3,)
    pattern: int  # 0 stripes, 1 checks, 2 print
    pattern_freq: float  # cycles per metre

    @classmethod
    def from_rng(cls, rng: np.random.Generator) -> Outfit:
        """A random but plausible outfit."""
        skins = np.array(
            [
                [0.93, 0.76, 0.64],
                [0.80, 0.60, 0.45],
                [0.55, 0.38, 0.26],
                [0.36, 0.24, 0.16],
            ]
        )
        return cls(
            skin=skins[rng.integers(len(skins))],
            hair=rng.uniform(0.05, 0.35) * np.array([1.0, 0.8, 0.6]),
            shirt=rng.uniform(0.1, 0.95, size=(2, 3)),
            trousers=rng.choice([np.array([0.15, 0.2, 0.4]), rng.uniform(0.1, 0.6, 3)]),
            shoes=rng.uniform(0.05, 0.3) * np.ones(3),
            pattern=int(rng.integers(3)),
            pattern_freq=float(rng.uniform(6, 14)),
        )


def clothing(
    seed: TextureSeed,
    outfit: Outfit,
    template_points: FloatArray,
    part_names: tuple[str, ...],
    part: IndexArray,
) -> FloatArray:
    """Colour (N, 3) of body surface points.

    Args:
        seed: noise tables.
        outfit: the person's colours.
        template_points: (N, 3) rest-pose coordinates of the points (body frame, m).
        part_names: body-part names, indexed by ``part``.
        part: (N,) body-part label of each point.
    """
    x, y, z = template_points.T
    if outfit.pattern == 0:
        mix = (np.sin(2 * np.pi * outfit.pattern_freq * z) > 0).astype(float)
    elif outfit.pattern == 1:
        f = outfit.pattern_freq
        mix = (
            (np.sin(2 * np.pi * f * z) > 0) ^ (np.sin(2 * np.pi * f * x) > 0)
        ).astype(float)
    else:
        inside, _ = disk_field(seed, template_points[:, [0, 2]] * 3 + 5.0, cell_m=0.35)
        mix = inside
    shirt = (1 - mix[:, None]) * outfit.shirt[0] + mix[:, None] * outfit.shirt[1]
    # Fabric grain, so plain areas still have a little texture.
    grain = 0.85 + 0.3 * fbm(seed, template_points + 40.0, 40.0, 3)
    name = np.array(part_names)[part]
    colour = np.tile(outfit.skin, (len(part), 1))
    is_shirt = np.isin(name, ["torso", "upper_arm_left", "upper_arm_right"])
    is_legs = np.char.startswith(name.astype(str), "upper_leg") | np.char.startswith(
        name.astype(str), "lower_leg"
    )
    is_feet = np.char.startswith(name.astype(str), "foot")
    colour[is_shirt] = shirt[is_shirt]
    colour[is_legs] = outfit.trousers
    colour[is_feet] = outfit.shoes
    # Hair: the top and back of the head.
    is_head = name == "head"
    head_top = z[is_head].max() if is_head.any() else 0.0
    is_hair = is_head & ((z > head_top - 0.07) | ((z > head_top - 0.17) & (y < -0.02)))
    colour[is_hair] = outfit.hair
    return np.clip(colour * grain[:, None], 0.0, 1.0)
