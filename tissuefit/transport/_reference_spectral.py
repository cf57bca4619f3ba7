"""The spectral reference tracer: multi-band MCML with fluorescence, one photon at a time.

The test oracle for the fast vectorised multi-band tracer. Each photon follows MCML (Wang, Jacques &
Zheng 1995, "MCML — Monte Carlo modeling of light transport in multi-layered tissues", Comput.
Methods Programs Biomed. 47:131) step by step — launch, hop, cross-or-not, drop, spin, roulette —
in the optical properties of its current band and medium. Fluorescence is the conversion of weight
between bands at an interaction, with isotropic re-emission, as in Welch et al. (1997),
"Propagation of fluorescent light", Lasers Surg. Med. 21:166.

What differs from single-band MCML:
- a photon carries one band at a time, drawn at launch with probability `band_power[b]`;
- at an interaction in band i of a medium with albedo a = mus/mut and conversion probability
  p = sum_j P[i, j], the weight w loses heat w (mua/mut - p); the rest R = w (a + p) converts
  with probability q = boost q_a / (1 + (boost - 1) q_a) (the odds boosted), q_a = p / (a + p), into band j (chosen with probability
  P[i, j] / p) with weight R q_a / q and an isotropic direction, or else scatters on in band i
  (Henyey–Greenstein) with weight R (1 - q_a) / (1 - q);
- regions (a sphere or box intersected with one layer) replace their layer's optical properties.
  A free path is a dimensionless optical depth tau = -ln(xi); the photon stops at the nearest of
  the interaction, a layer face or a region boundary, and at a face or boundary the unfinished
  optical depth is carried into the next medium (MCML's `sleft`). Regions have their layer's
  refractive index, so their boundaries neither reflect nor refract.

Nothing here is vectorised or traced: every number is a Python float, random numbers come from
`numpy.random.default_rng(seed)`, and the code favours being obviously right over being fast.
Units: lengths in cm, coefficients in 1/cm, the beam's polar angle in degrees, weights and tallies
as fractions of launched power [-].
"""

from __future__ import annotations

import math

import numpy as np

from ._reference import COS_ZERO, _Uniforms, fresnel, sample_hg_cosine

_REGION_KEYS = {
    "sphere": {"kind", "center", "radius", "layer", "mua", "mus", "g", "conversion"},
    "box": {"kind", "lower", "upper", "layer", "mua", "mus", "g", "conversion"},
}


# --------------------------------------------------------------------------------------------
# Input checks (everything is checked before any photon is traced)


def _floats(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    """`value` as a float64 array of `shape`, without NaN."""
    array = np.asarray(value, dtype=np.float64)
    if array.shape != shape:
        raise ValueError(f"{name} has shape {array.shape}; expected {shape}")
    if np.any(np.isnan(array)):
        raise ValueError(f"{name} contains NaN")
    return array


def _medium(name: str, mua, mus, g, conversion, bands: int) -> _Medium:
    """One medium's checked per-band optics: mua, mus [1/cm] finite >= 0, g in (-1, 1), conversion
    [-] finite >= 0 with row sums p_i <= mua_i / mut_i (so zero where mut_i = 0)."""
    mua, mus, g = (_floats(f"{name}.{k}", v, (bands,)) for k, v in (("mua", mua), ("mus", mus), ("g", g)))
    conversion = _floats(f"{name}.conversion", conversion, (bands, bands))
    for field, values in (("mua", mua), ("mus", mus), ("conversion", conversion)):
        if not np.all(np.isfinite(values)) or np.any(values < 0.0):
            raise ValueError(f"{name}.{field} must be finite and >= 0 (1/cm for mua, mus)")
    if np.any(np.abs(g) >= 1.0):
        raise ValueError(f"{name}.g must lie in (-1, 1); got {g.tolist()}")
    mut, p = mua + mus, conversion.sum(axis=1)
    limit = np.divide(mua, mut, out=np.zeros_like(mua), where=mut > 0.0)
    if np.any(p > limit * (1.0 + 1e-12)):
        raise ValueError(
            f"{name}.conversion: row sums p = {p.tolist()} exceed mua/mut = {limit.tolist()} "
            "(conversion includes the quantum yield and cannot exceed the absorbed fraction)"
        )
    return _Medium(mua, mus, g, conversion)


def _region(index: int, spec, layers: int, bands: int) -> _Region:
    """One checked region dict (unknown or missing keys are errors)."""
    name = f"regions[{index}]"
    if not isinstance(spec, dict) or spec.get("kind") not in _REGION_KEYS:
        raise ValueError(f"{name} must be a dict with kind 'sphere' or 'box'")
    expected = _REGION_KEYS[spec["kind"]]
    if set(spec) != expected:
        unknown, missing = sorted(set(spec) - expected), sorted(expected - set(spec))
        raise ValueError(f"{name}: unknown keys {unknown}, missing keys {missing}")
    layer = spec["layer"]
    if isinstance(layer, bool) or not isinstance(layer, (int, np.integer)) or not 0 <= layer < layers:
        raise ValueError(f"{name}.layer = {layer!r} must be an integer layer index in [0, {layers})")
    medium = _medium(name, spec["mua"], spec["mus"], spec["g"], spec["conversion"], bands)
    region = _Region(spec["kind"], int(layer), medium)
    if spec["kind"] == "sphere":
        center = _floats(f"{name}.center", spec["center"], (3,))
        radius = float(_floats(f"{name}.radius", spec["radius"], ()))
        if not np.all(np.isfinite(center)) or not 0.0 < radius < math.inf:
            raise ValueError(f"{name}: center [cm] must be finite and radius [cm] finite and > 0")
        region.center, region.radius = center.tolist(), radius
    else:
        lower = _floats(f"{name}.lower", spec["lower"], (3,))
        upper = _floats(f"{name}.upper", spec["upper"], (3,))
        if not np.all(lower < upper):
            raise ValueError(f"{name}: lower [cm] must be < upper [cm] on every axis (inf allowed)")
        region.lower, region.upper = lower.tolist(), upper.tolist()
    return region


def _overlap(a: _Region, b: _Region) -> bool:
    """Whether the closed shapes of two regions overlap or touch, ignoring their layer.

    Touching is refused too: a photon leaving one region straight into another would need a
    point-on-two-surfaces decision that rounding cannot make reliably."""
    if a.kind == "box" and b.kind == "box":
        return all(a.lower[k] <= b.upper[k] and b.lower[k] <= a.upper[k] for k in range(3))
    if a.kind == "sphere" and b.kind == "sphere":
        return math.dist(a.center, b.center) <= a.radius + b.radius
    sphere, box = (a, b) if a.kind == "sphere" else (b, a)
    nearest = [min(max(sphere.center[k], box.lower[k]), box.upper[k]) for k in range(3)]
    return math.dist(nearest, sphere.center) <= sphere.radius


# --------------------------------------------------------------------------------------------
# The scene as plain Python numbers


class _Medium:
    """Per-band optics of one medium (a layer or a region) as lists of floats: mua, mus, mut
    [1/cm], g [-], conversion rows P[i][j] [-] and their sums p[i] [-]."""

    def __init__(self, mua, mus, g, conversion):
        self.mua = [float(v) for v in mua]
        self.mus = [float(v) for v in mus]
        self.mut = [a + s for a, s in zip(self.mua, self.mus)]
        self.g = [float(v) for v in g]
        self.conversion = [[float(v) for v in row] for row in conversion]
        self.p = [sum(row) for row in self.conversion]

    def emission_band(self, band: int, xi: float) -> int:
        """Band j drawn with probability P[band][j] / p[band] from a uniform `xi` in [0, 1)."""
        row = self.conversion[band]
        target, total, chosen = xi * self.p[band], 0.0, band
        for j, value in enumerate(row):
            if value > 0.0:
                chosen = j  # the last band with P > 0 also catches rounding at the top end
                total += value
                if target < total:
                    return j
        return chosen


class _Region:
    """A sphere or box (cm) intersected with layer `layer`, with its own `_Medium`."""

    def __init__(self, kind: str, layer: int, medium: _Medium):
        self.kind, self.layer, self.medium = kind, layer, medium
        self.center, self.radius = [0.0, 0.0, 0.0], 0.0  # sphere [cm]
        self.lower, self.upper = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]  # box [cm]

    def contains(self, p: tuple[float, float, float]) -> bool:
        """Whether point `p` [cm] lies in the closed shape."""
        if self.kind == "sphere":
            return sum((p[k] - self.center[k]) ** 2 for k in range(3)) <= self.radius**2
        return all(self.lower[k] <= p[k] <= self.upper[k] for k in range(3))

    def distance(self, p, u, inside: bool) -> float:
        """Distance [cm] along unit direction `u` from `p` to where the ray leaves the shape
        (`inside`, >= 0) or first enters it (outside; inf if it does not, or only behind p)."""
        if self.kind == "sphere":
            oc = [p[k] - self.center[k] for k in range(3)]
            b = sum(oc[k] * u[k] for k in range(3))
            disc = b * b - (sum(v * v for v in oc) - self.radius**2)
            if disc < 0.0:
                return 0.0 if inside else math.inf  # (inside: p is on the surface, to rounding)
            root = math.sqrt(disc)
            near, far = -b - root, -b + root
        else:
            near, far = -math.inf, math.inf
            for k in range(3):
                if u[k] == 0.0:
                    if not inside and not self.lower[k] <= p[k] <= self.upper[k]:
                        return math.inf
                    continue
                ta, tb = (self.lower[k] - p[k]) / u[k], (self.upper[k] - p[k]) / u[k]
                near, far = max(near, min(ta, tb)), min(far, max(ta, tb))
        if inside:
            return max(far, 0.0)
        return near if 0.0 < near <= far else math.inf


class _Scene:
    """Plain-float layered tissue: indices n [-], faces z0, z1 [cm], layer media and regions."""

    def __init__(self, n, thickness, n_above, n_below, layer_media, regions):
        self.n = [float(v) for v in n]
        self.count = len(self.n)
        self.n_above, self.n_below = float(n_above), float(n_below)
        self.z0 = [float(sum(thickness[:i])) for i in range(self.count)]
        self.z1 = [z + float(t) for z, t in zip(self.z0, thickness)]
        self.thickness = [float(t) for t in thickness]
        self.layers = layer_media
        self.regions = regions
        self.regions_in = [[k for k, r in enumerate(regions) if r.layer == i] for i in range(self.count)]
        self.glass_top = all(m == 0.0 for m in layer_media[0].mut)

    def index_of(self, layer: int) -> float:
        """Refractive index of `layer`; -1 is the ambient medium above, `count` the one below."""
        if layer < 0:
            return self.n_above
        return self.n_below if layer >= self.count else self.n[layer]

    def region_at(self, layer: int, p) -> int:
        """Index of the region of `layer` containing point `p` [cm], or -1 for the layer itself."""
        for k in self.regions_in[layer]:
            if self.regions[k].contains(p):
                return k
        return -1

    def distance_to_region_boundary(self, photon: _Photon) -> tuple[float, int]:
        """(distance [cm], medium after the boundary: region index or -1) along the direction."""
        p, u = (photon.x, photon.y, photon.z), (photon.ux, photon.uy, photon.uz)
        if photon.region >= 0:
            return self.regions[photon.region].distance(p, u, inside=True), -1
        best, target = math.inf, -1
        for k in self.regions_in[photon.layer]:
            d = self.regions[k].distance(p, u, inside=False)
            if d < best:
                best, target = d, k
        return best, target


# --------------------------------------------------------------------------------------------
# Tallies


_BANDED = ("rd", "tt", "heat", "rd_fluor", "tt_fluor", "heat_fluor", "emitted", "converted_from")
"""Tallies with one entry per band; `*_fluor` count weight of photons that have converted."""


class _Tallies:
    """Weight per band of the current photon, and sums over photons of it and of its square."""

    def __init__(self, bands: int):
        self.photon = {k: [0.0] * bands for k in _BANDED}
        self.total = {k: [0.0] * bands for k in _BANDED}
        self.square = {k: [0.0] * bands for k in _BANDED}
        self.roulette = self.roulette_fluor = 0.0

    def add(self, name: str, band: int, w: float, converted: bool = False) -> None:
        """Weight `w` [-] to tally `name` in `band` (and to `name_fluor` for a converted photon)."""
        self.photon[name][band] += w
        if converted:
            self.photon[name + "_fluor"][band] += w

    def end_photon(self) -> None:
        """Add the current photon's tallies and their squares to the sums; reset them."""
        for name, values in self.photon.items():
            for b, v in enumerate(values):
                if v != 0.0:
                    self.total[name][b] += v
                    self.square[name][b] += v * v
                    values[b] = 0.0

    def finish(self, photons: int, rsp: float) -> dict:
        """Means per launched photon and standard errors sqrt(var / N) from per-photon moments."""
        out = {"rsp": np.asarray(rsp, dtype=np.float64)}
        for name in _BANDED:
            mean = np.asarray(self.total[name]) / photons
            var = np.maximum(np.asarray(self.square[name]) / photons - mean**2, 0.0) * photons / max(photons - 1, 1)
            out[name], out[name + "_stderr"] = mean, np.sqrt(var / photons)
        out["roulette"] = np.asarray(self.roulette / photons)
        out["roulette_fluor"] = np.asarray(self.roulette_fluor / photons)
        out["photons"] = np.asarray(photons)
        return out


# --------------------------------------------------------------------------------------------
# A photon's life


class _Photon:
    """One photon: position (x, y, z) [cm], unit direction (ux, uy, uz), weight w [-], band,
    layer, region (-1: the layer itself), unfinished optical depth `sleft` [-] (0: draw a new
    one), whether it is alive and whether it has converted (fluorescence)."""

    __slots__ = ("x", "y", "z", "ux", "uy", "uz", "w", "band", "layer", "region", "sleft", "alive", "converted", "index")

    def __init__(self, x, y, z, ux, uy, uz, w, band, layer, region):
        self.x, self.y, self.z, self.ux, self.uy, self.uz = x, y, z, ux, uy, uz
        self.w, self.band, self.layer, self.region = w, band, layer, region
        self.sleft, self.alive, self.converted = 0.0, w > 0.0, False
        self.index = 0


def specular(scene: _Scene, cos_i: float) -> tuple[float, float, float, int]:
    """MCML's specular reflectance at launch for incidence cosine `cos_i` from above.

    Returns (rsp [-], transmitted weight [-], cosine of the transmitted direction, layer entered).
    With glass on top (mua = mus = 0 in every band of layer 0) the reflections inside the plate
    are summed in closed form (MCML's combined formula) and the photon enters layer 1.
    """
    r1, cos_0 = fresnel(scene.n_above, scene.n[0], cos_i)
    if not scene.glass_top:
        return r1, 1.0 - r1, cos_0, 0
    if r1 >= 1.0:
        return 1.0, 0.0, cos_0, 1
    r2, cos_1 = fresnel(scene.n[0], scene.index_of(1), cos_0)
    rsp = r1 + (1.0 - r1) ** 2 * r2 / (1.0 - r1 * r2)
    return rsp, (1.0 - r1) * (1.0 - r2) / (1.0 - r1 * r2), cos_1, 1


def launch(scene: _Scene, polar: float, band: int, tallies: _Tallies) -> _Photon:
    """A photon of `band` entering at the origin from above at `polar` [rad] from the normal,
    refracted by Snell's law; with glass on top it starts at the plate's bottom face, shifted
    along x by thickness * tan(angle in glass), or is transmitted at once if the plate is alone."""
    dx, dz = math.sin(polar), math.cos(polar)
    _, w, cos_t, layer = specular(scene, dz)
    x = 0.0
    if layer == 1:
        cos_0 = fresnel(scene.n_above, scene.n[0], dz)[1]
        x = scene.thickness[0] * dx * scene.n_above / scene.n[0] / cos_0
        if scene.count == 1:
            if w > 0.0:
                tallies.add("tt", band, w)
            return _Photon(x, 0.0, scene.z1[0], 0.0, 0.0, 1.0, 0.0, band, 0, -1)
    z = scene.z0[layer]
    ux = dx * scene.n_above / scene.index_of(layer)
    return _Photon(x, 0.0, z, ux, 0.0, cos_t, w, band, layer, scene.region_at(layer, (x, 0.0, z)))


def distance_to_face(photon: _Photon, scene: _Scene) -> float:
    """Distance [cm] to the face of the current layer the photon heads for (inf if uz == 0)."""
    if photon.uz > 0.0:
        return (scene.z1[photon.layer] - photon.z) / photon.uz
    if photon.uz < 0.0:
        return (scene.z0[photon.layer] - photon.z) / photon.uz
    return math.inf


def hop(photon: _Photon, s: float) -> None:
    """Move the photon `s` [cm] along its direction."""
    photon.x += s * photon.ux
    photon.y += s * photon.uy
    photon.z += s * photon.uz


def cross_or_not(photon: _Photon, scene: _Scene, rand: _Uniforms, tallies: _Tallies) -> None:
    """At a layer face: Fresnel reflection (all-or-none), or transmission with Snell refraction,
    into the next layer (and whichever of its regions contains the point) or out of the tissue."""
    upward = photon.uz < 0.0
    here = photon.layer
    there = here - 1 if upward else here + 1
    n_here, n_there = scene.n[here], scene.index_of(there)
    r, cos_t = fresnel(n_here, n_there, abs(photon.uz))
    if rand.next_open_zero() <= r:
        photon.uz = -photon.uz
        return
    if there < 0 or there >= scene.count:
        tallies.add("rd" if upward else "tt", photon.band, photon.w, photon.converted)
        photon.w, photon.alive = 0.0, False
        return
    scale = n_here / n_there
    photon.ux *= scale
    photon.uy *= scale
    photon.uz = -cos_t if upward else cos_t
    photon.layer = there
    photon.region = scene.region_at(there, (photon.x, photon.y, photon.z))


def spin(photon: _Photon, g: float, rand: _Uniforms) -> None:
    """Henyey–Greenstein deflection (anisotropy `g` [-]) and uniform azimuth, MCML's update."""
    cos_theta = sample_hg_cosine(g, rand.next())
    sin_theta = math.sqrt(1.0 - cos_theta * cos_theta)
    psi = 2.0 * math.pi * rand.next()
    cos_psi, sin_psi = math.cos(psi), math.sin(psi)
    ux, uy, uz = photon.ux, photon.uy, photon.uz
    if abs(uz) > COS_ZERO:
        photon.ux, photon.uy = sin_theta * cos_psi, sin_theta * sin_psi
        photon.uz = cos_theta if uz > 0.0 else -cos_theta
    else:
        temp = math.sqrt(1.0 - uz * uz)
        photon.ux = sin_theta * (ux * uz * cos_psi - uy * sin_psi) / temp + ux * cos_theta
        photon.uy = sin_theta * (uy * uz * cos_psi + ux * sin_psi) / temp + uy * cos_theta
        photon.uz = -sin_theta * cos_psi * temp + uz * cos_theta


def emit_isotropic(photon: _Photon, rand: _Uniforms) -> None:
    """A direction uniform on the unit sphere (fluorescence re-emission)."""
    uz = 2.0 * rand.next() - 1.0
    psi = 2.0 * math.pi * rand.next()
    sin_theta = math.sqrt(max(0.0, 1.0 - uz * uz))
    photon.ux, photon.uy, photon.uz = sin_theta * math.cos(psi), sin_theta * math.sin(psi), uz


def drop(photon: _Photon, medium: _Medium, boost: float, rand: _Uniforms, tallies: _Tallies, hook=None) -> None:
    """An interaction: deposit heat w (mua/mut - p), then convert (fluorescence) or scatter the
    remaining R = w (a + p), with conversion probability q = boost q_a / (1 + (boost - 1) q_a), q_a = p/(a + p).

    `hook(event, photon, medium)`, if given, sees the photon arriving ("interaction", before
    anything changes) and, after a conversion, the converted photon at the same point ("emission")."""
    if hook is not None:
        hook("interaction", photon, medium)
    i, w = photon.band, photon.w
    mut, p = medium.mut[i], medium.p[i]
    albedo = medium.mus[i] / mut
    tallies.add("heat", i, w * (medium.mua[i] / mut - p), photon.converted)
    remaining = w * (albedo + p)
    if remaining == 0.0:  # mus = 0 and no conversion: fully absorbed
        photon.w, photon.alive = 0.0, False
        return
    q_a = p / (albedo + p)
    q = boost * q_a / (1.0 + (boost - 1.0) * q_a)
    if q > 0.0 and rand.next() < q:
        j = medium.emission_band(i, rand.next())
        photon.w, photon.band, photon.converted = remaining * q_a / q, j, True
        tallies.add("emitted", j, photon.w)
        tallies.add("converted_from", i, photon.w)
        if hook is not None:
            hook("emission", photon, medium)
        emit_isotropic(photon, rand)
    else:
        photon.w = remaining * (1.0 - q_a) / (1.0 - q)
        spin(photon, medium.g[i], rand)


def roulette(photon: _Photon, chance: float, rand: _Uniforms, tallies: _Tallies) -> None:
    """Russian roulette: survive with probability `chance` and weight w / chance, or die."""
    before = photon.w
    if before == 0.0:
        photon.alive = False
        return
    if rand.next() < chance:
        photon.w = before / chance
    else:
        photon.w, photon.alive = 0.0, False
    tallies.roulette += photon.w - before
    if photon.converted:
        tallies.roulette_fluor += photon.w - before


def hop_drop_spin(photon: _Photon, scene: _Scene, boost: float, rand: _Uniforms, tallies: _Tallies, hook=None) -> None:
    """One step: move to the nearest of the interaction (tau / mut), the layer face and a region
    boundary; at a face or boundary keep the unfinished optical depth in `sleft`."""
    medium = scene.layers[photon.layer] if photon.region < 0 else scene.regions[photon.region].medium
    mut = medium.mut[photon.band]
    if photon.sleft == 0.0:
        photon.sleft = -math.log(rand.next_open_zero())
    s = photon.sleft / mut if mut > 0.0 else math.inf
    d_face = distance_to_face(photon, scene)
    d_region, target = scene.distance_to_region_boundary(photon)
    if s <= d_face and s <= d_region:
        if math.isinf(s):  # uz == 0 where nothing interacts: never arrives (probability zero)
            photon.alive = False
            return
        hop(photon, s)
        photon.sleft = 0.0
        drop(photon, medium, boost, rand, tallies, hook)
    elif d_region < d_face:
        hop(photon, d_region)
        photon.sleft = max(photon.sleft - d_region * mut, 0.0)
        photon.region = target
    else:
        hop(photon, d_face)
        photon.z = scene.z1[photon.layer] if photon.uz > 0.0 else scene.z0[photon.layer]
        photon.sleft = max(photon.sleft - d_face * mut, 0.0)
        cross_or_not(photon, scene, rand, tallies)


# --------------------------------------------------------------------------------------------
# Entry point


def trace_spectral_reference(
    *, n, thickness, n_above, n_below, mua, mus, g, conversion, band_power, photons, seed,
    polar_deg=0.0, roulette_threshold=1e-4, roulette_chance=0.1, conversion_boost=1.0, regions=(),
    on_interaction=None,
) -> dict:
    """Trace `photons` photons one at a time through layered tissue in B bands with fluorescence.

    Arguments (L layers, B bands, band index increasing with wavelength):
    - `n` [L] refractive index [-] (the same in every band); `thickness` [L] [cm], the last may be
      inf; `n_above`, `n_below` ambient indices [-]. Layer i spans depth [z0_i, z1_i), z > 0 down.
    - `mua`, `mus` [L, B] [1/cm]: total absorption (fluorophores included) and scattering; `g`
      [L, B] [-] Henyey–Greenstein anisotropy.
    - `conversion` [L, B, B] [-]: P[l, i, j], weight moved from band i to band j per unit weight at
      an interaction in layer l (quantum yield included); row sums p[l, i] <= mua/mut.
    - `band_power` [B] [-]: source power per band (>= 0, sums to 1); a photon's band is drawn from it.
    - `photons` >= 1; `seed`: integer seed of `numpy.random.default_rng`.
    - `polar_deg` [deg] in [0, 90): pencil beam at the origin, in the x-z plane.
    - `roulette_threshold`, `roulette_chance` [-]: MCML's Russian roulette (1e-4, 0.1).
    - `conversion_boost` [-] > 0: conversion is sampled with odds boost times the analog odds and
      weights corrected, so results stay unbiased; weight is conserved only for boost = 1.
    - `regions`: dicts {"kind": "sphere", "center": (x, y, z), "radius": r} or {"kind": "box",
      "lower": (x, y, z), "upper": (x, y, z)} [cm, box bounds may be inf] with "layer": int and
      optics "mua", "mus" [B] [1/cm], "g" [B], "conversion" [B, B]. The shape intersected with its
      layer takes these optics; shapes in one layer must not overlap or touch (even outside it).
    - `on_interaction`: optional `hook(event, photon, medium)` called at every interaction (`drop`),
      e.g. to score a camera image; `photon.index` is the photon's number.

    A top layer with mua = mus = 0 in every band is glass (MCML's combined Rsp; no regions in it).
    Refused: a top layer that is glass in only some bands, a semi-infinite layer with mut = 0 in
    any band.

    Returns numpy arrays per launched photon: `rsp` (scalar); per band [B]: `rd`, `tt`, `heat`
    (weight escaping or absorbed in that band), `emitted` (by emission band), `converted_from` (by
    excitation band), `rd_fluor`, `tt_fluor`, `heat_fluor` (the same for photons that have
    converted); `roulette`, `roulette_fluor` (net weight roulette created, scalar); a standard
    error `<name>_stderr` [B] for each per-band tally (`rd_stderr`, `rd_fluor_stderr`, `tt_stderr`,
    ...) from per-photon first and second moments; `photons`. To float rounding, with boost = 1:
    rsp + sum(rd + tt + heat) - roulette = 1, sum(emitted) = sum(converted_from), and, where no
    converted photon converts again, sum(emitted) = sum(rd_fluor + tt_fluor + heat_fluor) - roulette_fluor.
    """
    n = _floats("n", n, (np.size(n),))
    layers = n.size
    band_power = _floats("band_power", band_power, (np.size(band_power),))
    bands = band_power.size
    thickness = _floats("thickness", thickness, (layers,))
    if layers < 1 or bands < 1:
        raise ValueError("at least one layer and one band are required")
    if np.any(n < 1.0) or not np.all(np.isfinite(n)) or not 1.0 <= n_above < math.inf or not 1.0 <= n_below < math.inf:
        raise ValueError("n, n_above, n_below must be finite and >= 1")
    if not np.all(thickness > 0.0) or not np.all(np.isfinite(thickness[:-1])):
        raise ValueError("thickness [cm] must be > 0 and finite, except the last layer's (may be inf)")
    if np.any(band_power < 0.0) or abs(float(band_power.sum()) - 1.0) > 1e-9:
        raise ValueError(f"band_power must be >= 0 and sum to 1; got {band_power.tolist()}")
    mua = _floats("mua", mua, (layers, bands))
    mus = _floats("mus", mus, (layers, bands))
    g = _floats("g", g, (layers, bands))
    conversion = _floats("conversion", conversion, (layers, bands, bands))
    media = [_medium(f"layer[{i}]", mua[i], mus[i], g[i], conversion[i], bands) for i in range(layers)]
    checked = [_region(k, r, layers, bands) for k, r in enumerate(regions)]
    for a in range(len(checked)):
        for b in range(a):
            if checked[a].layer == checked[b].layer and _overlap(checked[a], checked[b]):
                raise ValueError(f"regions[{b}] and regions[{a}] (layer {checked[a].layer}) overlap or touch")
    scene = _Scene(n, thickness, n_above, n_below, media, checked)
    if any(m > 0.0 for m in media[0].mut) and any(m == 0.0 for m in media[0].mut):
        raise ValueError("layer 0 has mua = mus = 0 in some bands only; a glass top must be glass in every band")
    if scene.glass_top and scene.regions_in[0]:
        raise ValueError("layer 0 is glass (MCML's combined Rsp); it cannot hold regions")
    if math.isinf(scene.thickness[-1]) and any(m == 0.0 for m in media[-1].mut):
        raise ValueError("the semi-infinite last layer has mua = mus = 0 in some band; photons would never stop")
    if isinstance(photons, bool) or not isinstance(photons, (int, np.integer)) or photons < 1:
        raise ValueError(f"photons = {photons!r} must be an integer >= 1")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed = {seed!r} must be an integer")
    if not 0.0 <= polar_deg < 90.0:
        raise ValueError(f"polar_deg = {polar_deg!r} must lie in [0, 90) deg")
    if not 0.0 < roulette_threshold < 1.0 or not 0.0 < roulette_chance <= 1.0:
        raise ValueError("roulette_threshold must lie in (0, 1) and roulette_chance in (0, 1]")
    if not 0.0 < conversion_boost < math.inf:
        raise ValueError(f"conversion_boost = {conversion_boost!r} must be finite and > 0")

    rand = _Uniforms(np.random.default_rng(seed))
    tallies = _Tallies(bands)
    cumulative = np.cumsum(band_power).tolist()
    last_band = max(b for b in range(bands) if band_power[b] > 0.0)
    polar = math.radians(polar_deg)
    boost, threshold, chance = float(conversion_boost), float(roulette_threshold), float(roulette_chance)
    for index in range(int(photons)):
        xi = rand.next()
        band = next((b for b in range(bands) if xi < cumulative[b] and band_power[b] > 0.0), last_band)
        photon = launch(scene, polar, band, tallies)
        photon.index = index
        while photon.alive:
            hop_drop_spin(photon, scene, boost, rand, tallies, on_interaction)
            if photon.alive and photon.w < threshold:
                roulette(photon, chance, rand, tallies)
        tallies.end_photon()
    return tallies.finish(int(photons), specular(scene, math.cos(polar))[0])
