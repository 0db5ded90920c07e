"""Deterministic procedural marine animals: starfish, sea cucumber, scallop, anemone, sponge and fish."""

from __future__ import annotations

import numpy as np
import trimesh

from seasynth.worker.scene.assets.geometry import (
    capped,
    cones,
    finish,
    hinged_pair,
    pick_colour,
    plates,
    revolve,
    ring_points,
    smoothstep,
    tubes,
    unit,
    valve,
    wave_field,
    widened,
)

STARFISH_PALETTE = np.array([[0.85, 0.40, 0.12], [0.70, 0.15, 0.12], [0.45, 0.20, 0.45],
                             [0.80, 0.62, 0.35], [0.55, 0.28, 0.15]])
CUCUMBER_PALETTE = np.array([[0.25, 0.16, 0.10], [0.10, 0.08, 0.07], [0.55, 0.42, 0.30],
                             [0.45, 0.18, 0.12], [0.35, 0.30, 0.22]])
SCALLOP_PALETTE = np.array([[0.85, 0.45, 0.20], [0.70, 0.30, 0.30], [0.85, 0.70, 0.55],
                            [0.55, 0.30, 0.45], [0.80, 0.65, 0.30]])
ANEMONE_PALETTE = np.array([[0.90, 0.50, 0.55], [0.90, 0.55, 0.20], [0.88, 0.85, 0.78],
                            [0.45, 0.60, 0.35], [0.55, 0.25, 0.45], [0.75, 0.15, 0.15]])
SPONGE_PALETTE = np.array([[0.90, 0.75, 0.25], [0.85, 0.45, 0.15], [0.50, 0.30, 0.55],
                           [0.50, 0.38, 0.25], [0.70, 0.25, 0.20], [0.55, 0.58, 0.62]])
FISH_BACK = np.array([[0.20, 0.28, 0.35], [0.28, 0.32, 0.20], [0.40, 0.32, 0.22],
                      [0.45, 0.20, 0.15], [0.30, 0.30, 0.32]])


def starfish(rng: np.random.Generator) -> trimesh.Trimesh:
    """Starfish 6-30 cm across: 5 arms (4 or 6 in a quarter of them) tapering from a central disc, flattened (a
    flat underside), their tips curled up a little (1.3k-2k triangles)."""
    arms = int(rng.choice([4, 5, 6], p=[0.1, 0.75, 0.15]))
    radius = rng.uniform(0.04, 0.15)  # centre to the longest arm's tip
    disc = radius * rng.uniform(0.2, 0.35)
    arm_len = radius * rng.uniform(0.85, 1.0, arms)
    arm_len[rng.integers(arms)] = radius
    curl = radius * rng.uniform(0.0, 0.25, arms)
    sharp = rng.uniform(2.0, 3.5)
    sides, sections = 24 * arms, 7
    theta = 2.0 * np.pi * np.arange(sides) / sides + rng.uniform(0.0, 2.0 * np.pi)
    sector = 2.0 * np.pi / arms
    arm = np.round((theta - theta[0]) / sector).astype(int) % arms
    u = np.abs((theta - theta[0]) / sector - np.round((theta - theta[0]) / sector)) * 2.0  # 0 on an arm, 1 between
    lobe = np.cos(0.5 * np.pi * u) ** sharp
    r = disc + (arm_len[arm] - disc) * lobe  # (sides,) outline
    half = radius * rng.uniform(0.08, 0.13) * (1.0 - 0.3 * lobe)  # half-thickness along each ray
    phi = np.linspace(-0.5 * np.pi, 0.5 * np.pi, sections + 2)[1:-1, None]  # (sections, 1) elevation
    h = r * np.cos(phi)  # horizontal distance
    z = half * np.sin(phi) * np.where(phi < 0, 0.35, 1.0) + curl[arm] * lobe**2 * (h / radius) ** 3
    rings = np.stack([h * np.cos(theta), h * np.sin(theta), z], -1)
    vertices, faces = capped(rings, np.array([[0.0, 0.0, -0.35 * half.max()], [0.0, 0.0, half.max()]]))
    colour = pick_colour(rng, STARFISH_PALETTE, 0.15)
    tip = np.clip(colour * 1.3 + 0.05, 0, 1)
    t = np.append(np.broadcast_to(h / radius, (sections, sides)).ravel(), [0.0, 0.0])[:, None]
    shade = 1.0 + 0.1 * wave_field(rng, vertices / radius, 12, 6.0)[:, None]
    belly = np.append(np.broadcast_to(phi < 0, (sections, sides)).ravel(), [True, False])[:, None]
    rgb = ((1 - t) * colour + t * tip) * shade * np.where(belly, 1.25, 1.0)
    return finish(vertices, faces, rgb)


def sea_cucumber(rng: np.random.Generator) -> trimesh.Trimesh:
    """Sea cucumber 10-35 cm long: a soft, slightly bent cylindrical body with rounded ends and a flat sole,
    wrinkled, with 20-60 conical papillae on its back and two rows of tube-feet bumps along its sole (<= 1.45k
    triangles)."""
    length = rng.uniform(0.10, 0.35)
    radius = length * rng.uniform(0.09, 0.15)
    sections, sides = 22, 16
    t = np.linspace(0.0, 1.0, sections + 2)[1:-1]
    bend = rng.uniform(-0.12, 0.12) * length
    centre = np.column_stack([length * (t - 0.5), bend * np.sin(np.pi * t), np.zeros(sections)])
    axis = unit(np.gradient(centre, axis=0))
    body_r = radius * np.sin(np.pi * t) ** 0.45 * (1.0 + 0.06 * np.sin(2 * np.pi * rng.uniform(3, 7) * t))
    rings = ring_points(centre, axis, body_r, sides)  # (sections, sides, 3)
    rings += 0.05 * radius * wave_field(rng, rings.reshape(-1, 3) / radius, 16, 2.5).reshape(sections, sides, 1) \
        * unit((rings - centre[:, None]).reshape(-1, 3)).reshape(sections, sides, 3)
    rings[..., 2] = np.where(rings[..., 2] < -0.5 * radius, -0.5 * radius + 0.2 * (rings[..., 2] + 0.5 * radius),
                             rings[..., 2])  # the sole
    ends = np.array([[-0.5 * length, 0.0, 0.0], [0.5 * length, 0.0, 0.0]])
    body_v, body_f = capped(rings, ends)
    normal = unit((rings - centre[:, None]).reshape(-1, 3))
    n = int(rng.integers(20, 61))
    top = np.flatnonzero((normal[:, 2] > 0.2) & (np.repeat(t, sides) > 0.1) & (np.repeat(t, sides) < 0.9))
    feet = np.flatnonzero((np.abs(normal[:, 2] + 0.55) < 0.15) & (np.repeat(t, sides) > 0.15)
                          & (np.repeat(t, sides) < 0.85))[::2]
    pick = np.concatenate([rng.choice(top, n, replace=False), feet])
    tall = np.concatenate([radius * rng.uniform(0.15, 0.45, n), np.full(len(feet), 0.1 * radius)])
    base = np.concatenate([radius * rng.uniform(0.06, 0.12, n), np.full(len(feet), 0.05 * radius)])
    spike_v, spike_f = cones(body_v[pick] - normal[pick] * base[:, None], normal[pick], tall + base, base, 5)
    colour = pick_colour(rng, CUCUMBER_PALETTE, 0.2)
    mottle = 1.0 + 0.15 * wave_field(rng, body_v / radius, 12, 2.0)[:, None]
    spike_rgb = np.repeat(np.clip(colour * 1.4 + 0.06, 0, 1)[None], len(spike_v), axis=0)
    return finish(np.concatenate([body_v, spike_v]), np.concatenate([body_f, spike_f + len(body_v)]),
                  np.concatenate([colour * mottle, spike_rgb]))


def reach(p: np.ndarray, d: np.ndarray, normals: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(s,) distance from `p: (2,)` along unit `d: (s, 2)` to the border of the convex polygon {x: normals @ x <=
    offsets} (normals (k, 2), offsets (k,)), which holds p."""
    along = d @ normals.T  # (s, k)
    gap = offsets - normals @ p  # (k,) >= 0
    with np.errstate(divide="ignore"):
        return np.where(along > 1e-12, gap / np.where(along > 1e-12, along, 1.0), np.inf).min(axis=1)


def scallop(rng: np.random.Generator) -> trimesh.Trimesh:
    """Scallop 5-16 cm wide: two fan-shaped valves with 14-24 strong radial ribs and a straight hinge with its two
    ears, opened 3-15 degrees (1.5k triangles)."""
    a = rng.uniform(0.025, 0.075)  # the fan's radius
    alpha = np.deg2rad(rng.uniform(42.0, 55.0))  # half-angle of the fan at the umbo
    ear = a * rng.uniform(0.35, 0.5)
    hinge = -1.05 * a
    umbo = np.array([0.0, -0.85 * a])
    ribs = int(rng.integers(14, 25))
    sides, rings = 48, 8
    phi = 2.0 * np.pi * np.arange(sides) / sides
    d = np.column_stack([np.cos(phi), np.sin(phi)])
    pu = umbo @ d.T
    circle = -pu + np.sqrt(pu * pu - (umbo @ umbo - a * a))
    wedge = reach(umbo - [0.0, hinge], d, np.array([[-np.cos(alpha), -np.sin(alpha)], [np.cos(alpha), -np.sin(alpha)]]),
                  np.zeros(2))
    box = reach(umbo, d, np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, -1.0], [0.0, 1.0]]), np.array([ear, ear, -hinge, 0.0]))
    rib = np.abs(np.cos(0.5 * np.pi * ribs * (phi - 0.5 * np.pi) / alpha))  # `ribs` ribs across the fan
    r = np.maximum(np.minimum(circle, wedge) * (1.0 + 0.03 * rib), box)  # a scalloped edge, a straight hinge
    rho = (np.arange(1, rings + 1) / rings)[:, None]
    xy = umbo + rho[..., None] * (r[:, None] * d)
    c = a * rng.uniform(0.18, 0.3)
    z = c * (1.0 - rho**2) ** 0.5 * (1.0 + 0.15 * rib)
    vertices, faces = valve(umbo, xy, z, c)
    shell_v, shell_f = hinged_pair(vertices, faces, hinge, np.deg2rad(rng.uniform(3.0, 15.0)))
    colour = pick_colour(rng, SCALLOP_PALETTE, 0.15)
    rho_v = np.concatenate([[0.0], np.repeat(rho[:, 0], sides), [-1.0]])
    rib_v = np.concatenate([[1.0], np.tile(rib, rings), [1.0]])
    shade = (0.8 + 0.2 * rib_v) * (0.9 + 0.1 * np.sin(2.0 * np.pi * rng.uniform(3.0, 7.0) * rho_v))
    rgb = np.where(rho_v[:, None] < 0, np.clip(colour * 1.2 + 0.15, 0, 1), colour * shade[:, None])
    return finish(shell_v, shell_f, np.concatenate([rgb, rgb]))


def anemone(rng: np.random.Generator) -> trimesh.Trimesh:
    """Sea anemone 2-19 cm tall and up to 30 cm across its tentacles: a column (1-4 cm radius) flaring to an oral
    disc, crowned by 20-48 tapering, curving tentacles in two whorls (1.2k-2.5k triangles)."""
    rc = rng.uniform(0.01, 0.04)
    hc = rc * rng.uniform(1.0, 3.0)
    flare = rng.uniform(1.1, 1.5)
    r = rc * np.array([1.15, 1.1, 0.95, 1.0, flare, 0.75 * flare, 0.3])
    z = np.array([0.0, 0.1 * hc, 0.5 * hc, 0.8 * hc, hc, hc + 0.05 * rc, hc - 0.05 * rc])
    col_v, col_f = revolve(r, z, 24)
    col_v = widened(col_v, 1.0 + 0.04 * wave_field(rng, col_v / rc, 8, 1.5))
    n = int(rng.integers(20, 49))
    whorl = np.arange(n) % 2
    angle = 2.0 * np.pi * (np.arange(n) + 0.5 * whorl) / n + rng.normal(0.0, 0.05, n)
    out = np.column_stack([np.cos(angle), np.sin(angle), np.zeros(n)])
    base = out * (rc * flare * (0.9 - 0.3 * whorl))[:, None] + [0.0, 0.0, hc]
    length = rc * rng.uniform(1.0, 2.2) * rng.uniform(0.8, 1.1, n) * (1.0 - 0.25 * whorl)
    rise = np.deg2rad(rng.uniform(25.0, 60.0, n))
    droop = rng.uniform(0.15, 0.8, n)
    s = np.linspace(0.0, 1.0, 6)
    lead = out * np.cos(rise)[:, None] + np.array([0.0, 0.0, 1.0]) * np.sin(rise)[:, None]
    sag = 0.5 * out - [0.0, 0.0, 0.7]
    centre = base[:, None] + length[:, None, None] * (s[None, :, None] * lead[:, None]
                                                      + (droop[:, None, None] * s[None, :, None] ** 2) * sag[:, None])
    tangent = unit((lead[:, None] + 2.0 * droop[:, None, None] * s[None, :, None] * sag[:, None]).reshape(-1, 3))
    thick = (rc * rng.uniform(0.08, 0.15) * (1.0 - 0.85 * s))[None].repeat(n, 0)
    ten_v, ten_f = tubes(ring_points(centre.reshape(-1, 3), tangent, thick.ravel(), 4).reshape(n, 6, 4, 3))
    body, tips = pick_colour(rng, ANEMONE_PALETTE, 0.15), pick_colour(rng, ANEMONE_PALETTE, 0.15)
    shade = np.repeat(0.8 + 0.4 * s, 4)
    ten_rgb = np.tile(tips[None] * shade[:, None], (n, 1))
    return finish(np.concatenate([col_v, ten_v]), np.concatenate([col_f, ten_f + len(col_v)]),
                  np.concatenate([np.repeat(body[None], len(col_v), 0), ten_rgb]))


def sponge(rng: np.random.Generator) -> trimesh.Trimesh:
    """Sponge: a barrel or vase 10-50 cm tall (and narrower) with its central cavity open at the top (half the
    variants; 948 triangles), or a lumpy encrusting mound 10-40 cm across and 2-15 cm high with dark oscula (1280
    triangles)."""
    colour = pick_colour(rng, SPONGE_PALETTE, 0.15)
    if rng.random() < 0.5:
        height = rng.uniform(0.10, 0.50)
        r0 = height * rng.uniform(0.12, 0.22)
        t = np.linspace(0.0, 1.0, 8)
        outer = r0 * (1.0 + rng.uniform(0.1, 0.5) * np.sin(np.pi * t) ** 1.5 + rng.uniform(0.0, 0.5) * t)  # <= height / 2
        wall = rng.uniform(0.25, 0.45)
        floor = height * rng.uniform(0.2, 0.4)
        z_in = floor + (height - floor) * t[::-1][:-1]  # the cavity's wall, down from the lip
        r = np.concatenate([[0.5 * r0], outer, (1 - wall) * np.interp(z_in, height * t, outer),
                            [0.5 * (1 - wall) * r0]])
        z = np.concatenate([[0.0], height * t, z_in, [floor]])
        vertices, faces = revolve(r, z, 28)
        vertices = widened(vertices, 1.0 + 0.06 * wave_field(rng, vertices / r0, 16, 1.5))
        inside = np.hypot(vertices[:, 0], vertices[:, 1]) < np.interp(vertices[:, 2], height * t, (1 - wall) * outer)
        shade = np.where(inside & (vertices[:, 2] > 0.5 * floor), 0.55, 1.0)
    else:
        sphere = trimesh.creation.icosphere(subdivisions=3)
        d = np.asarray(sphere.vertices)
        bumps = unit(rng.normal(size=(int(rng.integers(3, 8)), 3)) + [0.0, 0.0, 1.2])
        lobes = np.exp((d @ bumps.T - 1.0) / 0.08)  # (V, bumps)
        rad = 1.0 + 0.35 * lobes.max(axis=1) + 0.1 * wave_field(rng, d, 16, 2.5)
        width = rng.uniform(0.10, 0.40)
        axes = 0.5 * width * np.array([1.0, rng.uniform(0.6, 1.0), rng.uniform(0.25, 0.6)])
        vertices = d * rad[:, None] * axes
        floor = -0.3 * axes[2]
        vertices[:, 2] = np.where(vertices[:, 2] < floor, floor + 0.1 * (vertices[:, 2] - floor), vertices[:, 2])
        vertices *= width / np.ptp(vertices[:, :2], axis=0).max()  # `width` across, whatever the lobes
        faces = np.asarray(sphere.faces)
        shade = 1.0 - 0.6 * smoothstep(0.97, 0.995, (d @ bumps.T).max(axis=1))  # oscula atop the lobes
    mottle = 1.0 + 0.1 * wave_field(rng, vertices * 20.0, 12, 1.0)
    return finish(vertices, faces, colour * (shade * mottle)[:, None])


def fish(rng: np.random.Generator) -> trimesh.Trimesh:
    """Fish 9-60 cm long, nose along +x and back up (+z), its origin at its bounding box's centre (to hang in the
    water column): a fusiform body of one of three plans (slender, deep-bodied, flat: a flatfish lying on its
    side), a forked tail, a dorsal fin (a flatfish: a fringe along each side), two pectoral fins and two eyes
    (<= 680 triangles)."""
    plan = int(rng.integers(3))  # 0 slender, 1 deep-bodied, 2 flat
    length = rng.uniform(0.10, 0.60)
    height = length / (rng.uniform(4.5, 6.0), rng.uniform(2.0, 2.8), rng.uniform(7.0, 10.0))[plan]
    width = height * (rng.uniform(0.5, 0.7), rng.uniform(0.3, 0.45), rng.uniform(4.0, 5.0))[plan]
    body_len = 0.8 * length
    sections, sides = 16, 14
    u = np.linspace(0.0, 1.0, sections + 2)[1:-1]  # tail (0) to nose (1)
    shape = 0.1 + 0.9 * np.sin(np.pi * u ** rng.uniform(0.75, 0.95)) ** 0.7
    x = body_len * (u - 0.6)
    theta = 2.0 * np.pi * np.arange(sides) / sides
    belly = 1.0 - 0.15 * (np.sin(theta) < 0)  # a little flatter below
    rings = np.stack([np.broadcast_to(x[:, None], (sections, sides)),
                      0.5 * width * shape[:, None] * np.cos(theta),
                      0.5 * height * shape[:, None] * np.sin(theta) * belly], -1)
    body_v, body_f = capped(rings, np.array([[x[0] - 0.03 * body_len, 0.0, 0.0], [x[-1] + 0.03 * body_len, 0.0, 0.0]]))
    tail_x = x[0] - 0.02 * body_len
    lobe, span = (0.5 * height, 0.5 * width)[plan == 2] * rng.uniform(0.8, 1.1), 0.2 * length
    fork = rng.uniform(0.25, 0.6) * span
    tail = np.array([[fork, 0.0], [span, lobe], [0.0, 0.2 * lobe], [-0.05 * span, 0.0], [0.0, -0.2 * lobe],
                     [span, -lobe]])  # star-shaped about the fork's notch, its first corner
    up = np.array([[0.0, 1.0, 0.0]]) if plan == 2 else np.array([[0.0, 0.0, 1.0]])
    fin_t = np.maximum(0.004 * length, 0.0015)
    parts = [plates(tail, np.array([[tail_x, 0.0, 0.0]]), np.array([[-1.0, 0.0, 0.0]]), up, np.array([fin_t]))]
    base = 0.35 * body_len
    crest = height * rng.uniform(0.3, 0.6) if plan < 2 else width * 0.12
    dorsal = np.array([[-0.5 * base, -0.1 * crest], [0.5 * base, -0.1 * crest], [0.2 * base, 0.6 * crest],
                       [-0.3 * base, crest]])
    side = (0.5 * height, 0.5 * width)[plan == 2]
    at = np.interp(0.5, u, shape)
    for sign in ((1.0,), (1.0, -1.0))[plan == 2]:  # a flatfish's dorsal and anal fins fringe both of its sides
        parts.append(plates(dorsal, np.array([[body_len * -0.1, 0.0, 0.0]]) + sign * side * at * 0.85 * up,
                            np.array([[1.0, 0.0, 0.0]]), sign * up, np.array([fin_t])))
    fin = np.array([[0.0, -0.25], [1.0, -0.05], [0.9, 0.2], [0.0, 0.25]]) * 0.18 * length
    for sign in (1.0, -1.0):
        e1 = unit(np.array([[-1.0, 0.6 * sign, -0.25 * (plan < 2)]]))
        e2 = unit(np.cross([0.0, 0.0, 1.0], e1))
        at = np.interp(0.7, u, shape)
        parts.append(plates(fin, np.array([[body_len * 0.1, sign * 0.4 * width * at, -0.15 * height * at]]), e1, e2,
                            np.array([fin_t])))
    eye = trimesh.creation.icosphere(subdivisions=1)
    eye_r = 0.035 * length * (1.0 if plan < 2 else 0.8)
    at = np.interp(0.88, u, shape)
    spots = ([0.0, 0.42 * width * at, 0.15 * height * at], [0.0, -0.42 * width * at, 0.15 * height * at]) if plan < 2 \
        else ([0.0, 0.12 * width, 0.4 * height * at], [0.0, -0.12 * width, 0.4 * height * at])
    for y in spots:
        parts.append((np.asarray(eye.vertices) * eye_r + [0.28 * body_len, y[1], y[2]], np.asarray(eye.faces)))
    back = pick_colour(rng, FISH_BACK, 0.2)
    pale = np.clip(back * 0.4 + rng.uniform(0.45, 0.6), 0, 1)
    level = smoothstep(-0.4, 0.5, body_v[:, 2] / (0.5 * height)) if plan < 2 else np.ones(len(body_v))
    bars = 1.0 - 0.25 * (rng.random() < 0.3) * (np.sin(body_v[:, 0] / length * rng.uniform(25, 40)) > 0.5)
    rgb = [(level[:, None] * back + (1 - level[:, None]) * pale) * bars[:, None]]
    rgb += [np.repeat(back[None] * 0.8, len(v), 0) for v, _ in parts[:-2]]
    rgb += [np.repeat([[0.03, 0.03, 0.04]], len(v), 0) for v, _ in parts[-2:]]
    vertices, faces, offset = [body_v], [body_f], len(body_v)
    for v, f in parts:
        vertices.append(v), faces.append(f + offset)
        offset += len(v)
    return finish(np.concatenate(vertices), np.concatenate(faces), np.concatenate(rgb), centred=True)
