"""The reference tracer: MCML one photon at a time, in plain Python.

This is the test oracle for the fast vectorised tracer (`trace`). It follows MCML (Wang, Jacques &
Zheng 1995, "MCML — Monte Carlo modeling of light transport in multi-layered tissues") step by
step, with MCML's names for the steps of a photon's life:

- `launch`: specular reflection at the surface (deterministic, MCML's combined formula when the
  top layer is glass) and Snell refraction into the tissue;
- `step_size`: a new free path `-ln(xi)/mut`, or the unfinished part `sleft` of the last one;
- `distance_to_face` and `hop`: the hit test against the current layer's faces;
- `cross_or_not`: Fresnel reflection (all-or-none) or transmission at an interface;
- `drop`: implicit capture, `dw = w mua / mut`;
- `spin`: Henyey–Greenstein deflection with MCML's direction update;
- `roulette`: Russian roulette below a weight threshold.

Nothing here is vectorised or traced: every number is a Python float, random numbers come from
`numpy.random.default_rng(seed)`, and the code favours being obviously right over being fast.
Units: lengths in cm, coefficients in 1/cm.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from .._checks import check_positive_int
from .._outcome import Outcome
from ..scene import LayeredTissue, Scene
from ._config import TallySpec, TraceOptions
from ._result import TraceResult, bin_measures

COS_ZERO = 1.0 - 1e-12
"""MCML's COSZERO: a cosine above this is treated as exactly normal (no division by sin)."""

COS_90D = 1e-6
"""MCML's COS90D: a cosine below this is treated as grazing incidence (reflectance 1)."""


# --------------------------------------------------------------------------------------------
# The scene as plain Python numbers


class _Layers:
    """Plain-float view of a `LayeredTissue` (lengths in cm, coefficients in 1/cm)."""

    def __init__(self, tissue: LayeredTissue):
        def floats(values):
            return [float(v) for v in np.asarray(values, dtype=np.float64).reshape(-1)]

        self.n = floats(tissue.n)
        self.mua = floats(tissue.mua)
        self.mus = floats(tissue.mus)
        self.g = floats(tissue.g)
        self.thickness = floats(tissue.thickness)
        self.n_above = float(np.asarray(tissue.n_above))
        self.n_below = float(np.asarray(tissue.n_below))
        self.count = len(self.n)
        self.mut = [a + s for a, s in zip(self.mua, self.mus)]
        self.z0 = [sum(self.thickness[:i]) for i in range(self.count)]
        self.z1 = [z + t for z, t in zip(self.z0, self.thickness)]
        # A semi-infinite glass last layer is refused by LayeredTissue itself.

    def is_glass(self, layer: int) -> bool:
        """A layer with mua = mus = 0: crossed without interaction."""
        return self.mut[layer] == 0.0

    def index_of(self, medium: int) -> float:
        """Refractive index of layer `medium`; -1 is the ambient medium above, `count` the one below."""
        if medium < 0:
            return self.n_above
        if medium >= self.count:
            return self.n_below
        return self.n[medium]


# --------------------------------------------------------------------------------------------
# Random numbers


class _Uniforms:
    """Uniform numbers in [0, 1) from `numpy.random.default_rng(seed)`, drawn in blocks."""

    def __init__(self, rng: np.random.Generator, block: int = 1 << 16):
        self._rng = rng
        self._block = block
        self._buffer: list[float] = []
        self._next = 0

    def next(self) -> float:
        """One uniform number in [0, 1)."""
        if self._next == len(self._buffer):
            self._buffer = self._rng.random(self._block).tolist()
            self._next = 0
        self._next += 1
        return self._buffer[self._next - 1]

    def next_open_zero(self) -> float:
        """One uniform number in (0, 1] (safe for `log`, and `xi <= 0` never holds)."""
        return 1.0 - self.next()


# --------------------------------------------------------------------------------------------
# Interface physics


def fresnel(n1: float, n2: float, cos_i: float) -> tuple[float, float]:
    """Unpolarised Fresnel reflectance from index `n1` into `n2` (MCML's `RFresnel`).

    Arguments: `n1`, `n2` refractive indices [-]; `cos_i` cosine of the angle of incidence, in [0, 1].
    Returns `(reflectance [-], cos_t)` with `cos_t` the cosine of the transmission angle; past the
    critical angle (sin_t >= 1) the reflectance is 1 and `cos_t` is 0.
    """
    if n1 == n2:
        return 0.0, cos_i
    if cos_i > COS_ZERO:
        return ((n1 - n2) / (n1 + n2)) ** 2, cos_i
    if cos_i < COS_90D:
        return 1.0, 0.0
    sin_i = math.sqrt(1.0 - cos_i * cos_i)
    sin_t = n1 * sin_i / n2
    if sin_t >= 1.0:
        return 1.0, 0.0
    cos_t = math.sqrt(1.0 - sin_t * sin_t)
    cos_plus = cos_i * cos_t - sin_i * sin_t  # cos(i + t)
    cos_minus = cos_i * cos_t + sin_i * sin_t  # cos(i - t)
    sin_plus = sin_i * cos_t + cos_i * sin_t  # sin(i + t)
    sin_minus = sin_i * cos_t - cos_i * sin_t  # sin(i - t)
    r = 0.5 * sin_minus**2 * (cos_minus**2 + cos_plus**2) / (sin_plus**2 * cos_minus**2)
    return r, cos_t


def sample_hg_cosine(g: float, xi: float) -> float:
    """Cosine of a Henyey–Greenstein deflection angle for anisotropy `g` [-] and uniform `xi`."""
    if g == 0.0:
        return 2.0 * xi - 1.0
    temp = (1.0 - g * g) / (1.0 - g + 2.0 * g * xi)
    cos_theta = (1.0 + g * g - temp * temp) / (2.0 * g)
    return min(1.0, max(-1.0, cos_theta))


# --------------------------------------------------------------------------------------------
# Tallies


def _bin(value: float, width: float, count: int) -> int:
    """MCML's bin index floor(value / width), the last bin collecting overflow."""
    return min(int(value / width), count - 1)


class _Tallies:
    """Raw weight sums; normalised per photon and per bin size by `finish`.

    rd, a, tt and rd_r are kept per batch, for batch-means standard errors.
    """

    def __init__(self, spec: TallySpec, layers: _Layers, batches: int):
        self.spec = spec
        self.batch = 0
        self.rsp = 0.0
        self.roulette = 0.0  # net weight created by roulette (zero-mean)
        self.rd = [0.0] * batches
        self.a = [0.0] * batches
        self.tt = [0.0] * batches
        nr, nz, na = spec.nr, spec.nz, spec.na
        want = spec.wants
        self.rd_r = [[0.0] * nr for _ in range(batches)] if want("rd_r") else None
        self.rd_a = [0.0] * na if want("rd_a") else None
        self.rd_ra = np.zeros((nr, na)) if want("rd_ra") else None
        self.tt_r = [0.0] * nr if want("tt_r") else None
        self.tt_a = [0.0] * na if want("tt_a") else None
        self.tt_ra = np.zeros((nr, na)) if want("tt_ra") else None
        self.a_z = [0.0] * nz if want("a_z") else None
        self.a_rz = np.zeros((nr, nz)) if want("a_rz") else None
        self.a_layer = [0.0] * layers.count if want("a_layer") else None

    def absorb(self, dw: float, x: float, y: float, z: float, layer: int) -> None:
        """Weight `dw` absorbed at (x, y, z) [cm] in `layer`."""
        self.a[self.batch] += dw
        spec = self.spec
        if self.a_layer is not None:
            self.a_layer[layer] += dw
        if self.a_z is not None or self.a_rz is not None:
            iz = _bin(z, spec.dz, spec.nz)
            if self.a_z is not None:
                self.a_z[iz] += dw
            if self.a_rz is not None:
                self.a_rz[_bin(math.hypot(x, y), spec.dr, spec.nr), iz] += dw

    def escape(self, w: float, x: float, y: float, exit_angle: float, top: bool) -> None:
        """Weight `w` leaving the tissue at (x, y) [cm], at `exit_angle` [rad] from the normal,
        through the top surface (diffuse reflectance) or the bottom (transmittance)."""
        spec = self.spec
        ir = _bin(math.hypot(x, y), spec.dr, spec.nr)
        ia = _bin(exit_angle, spec.da, spec.na)
        if top:
            self.rd[self.batch] += w
            if self.rd_r is not None:
                self.rd_r[self.batch][ir] += w
            if self.rd_a is not None:
                self.rd_a[ia] += w
            if self.rd_ra is not None:
                self.rd_ra[ir, ia] += w
        else:
            self.tt[self.batch] += w
            if self.tt_r is not None:
                self.tt_r[ir] += w
            if self.tt_a is not None:
                self.tt_a[ia] += w
            if self.tt_ra is not None:
                self.tt_ra[ir, ia] += w

    def finish(self, photons: int, batch_sizes: np.ndarray) -> dict:
        """Normalise as MCML does and compute batch-means standard errors."""
        spec = self.spec
        dz = spec.dz
        ring_area, solid_angle, projected = bin_measures(spec)  # [cm^2], [sr], [sr]

        def total(per_batch) -> float:
            return float(np.sum(per_batch)) / photons

        def stderr(per_batch) -> np.ndarray:
            # x_b = batch sum / batch size; stderr = sqrt(var(x_b, ddof=1) / B).
            sums = np.asarray(per_batch, dtype=np.float64)
            means = sums / batch_sizes.reshape((-1,) + (1,) * (sums.ndim - 1))
            if len(batch_sizes) < 2:
                return np.full(means.shape[1:], np.nan)
            return np.sqrt(np.var(means, axis=0, ddof=1) / len(batch_sizes))

        out = {
            "rsp": self.rsp / photons,
            "roulette": self.roulette / photons,
            "rd": total(self.rd),
            "a": total(self.a),
            "tt": total(self.tt),
            "rd_stderr": stderr(self.rd),
            "a_stderr": stderr(self.a),
            "tt_stderr": stderr(self.tt),
        }
        if self.rd_r is not None:
            rd_r = np.asarray(self.rd_r)
            out["rd_r"] = rd_r.sum(axis=0) / (photons * ring_area)
            out["rd_r_stderr"] = stderr(rd_r) / ring_area
        if self.rd_a is not None:
            out["rd_a"] = np.asarray(self.rd_a) / (photons * solid_angle)
        if self.rd_ra is not None:
            out["rd_ra"] = self.rd_ra / (photons * ring_area[:, None] * projected[None, :])
        if self.tt_r is not None:
            out["tt_r"] = np.asarray(self.tt_r) / (photons * ring_area)
        if self.tt_a is not None:
            out["tt_a"] = np.asarray(self.tt_a) / (photons * solid_angle)
        if self.tt_ra is not None:
            out["tt_ra"] = self.tt_ra / (photons * ring_area[:, None] * projected[None, :])
        if self.a_z is not None:
            out["a_z"] = np.asarray(self.a_z) / (photons * dz)
        if self.a_rz is not None:
            out["a_rz"] = self.a_rz / (photons * ring_area[:, None] * dz)
        if self.a_layer is not None:
            out["a_layer"] = np.asarray(self.a_layer) / photons
        return out


# --------------------------------------------------------------------------------------------
# A photon's life


class _Photon:
    """State of one photon: position (x, y, z) [cm], unit direction (ux, uy, uz), weight w [-],
    current layer, unfinished dimensionless step `sleft` [-] and whether it is alive."""

    __slots__ = ("x", "y", "z", "ux", "uy", "uz", "w", "layer", "sleft", "alive")

    def __init__(self, x, y, z, ux, uy, uz, w, layer):
        self.x, self.y, self.z = x, y, z
        self.ux, self.uy, self.uz = ux, uy, uz
        self.w = w
        self.layer = layer
        self.sleft = 0.0
        self.alive = w > 0.0


def launch(x: float, y: float, d: tuple[float, float, float], layers: _Layers, tallies: _Tallies) -> _Photon:
    """Enter the tissue at (x, y, 0) [cm] with incident unit direction `d` (uz > 0) from above.

    The specular reflectance is tallied deterministically and the photon keeps weight 1 - Rsp.
    If layer 0 is glass, MCML's combined specular reflectance of the glass plate is used and the
    photon starts at the glass's bottom face; if the glass is the only layer, the transmitted part is
    tallied at once and the returned photon is dead.
    """
    dx, dy, dz = d
    n_above, n0 = layers.n_above, layers.n[0]
    r1, cos_0 = fresnel(n_above, n0, dz)
    if not layers.is_glass(0):
        tallies.rsp += r1
        scale = n_above / n0
        return _Photon(x, y, 0.0, dx * scale, dy * scale, cos_0, 1.0 - r1, 0)

    # Glass on top: multiple reflections inside the plate are summed in closed form.
    n1 = layers.index_of(1)
    if r1 >= 1.0:
        tallies.rsp += 1.0
        return _Photon(x, y, 0.0, 0.0, 0.0, 1.0, 0.0, 0)
    r2, cos_1 = fresnel(n0, n1, cos_0)
    rsp = r1 + (1.0 - r1) ** 2 * r2 / (1.0 - r1 * r2)
    transmitted = (1.0 - r1) * (1.0 - r2) / (1.0 - r1 * r2)
    tallies.rsp += rsp
    # Lateral shift across the plate: thickness * tan(angle in glass), along the incidence azimuth.
    scale_0 = n_above / n0
    shift = layers.thickness[0] / cos_0
    x, y = x + shift * dx * scale_0, y + shift * dy * scale_0
    scale_1 = n_above / n1
    if layers.count == 1:
        if transmitted > 0.0:
            tallies.escape(transmitted, x, y, math.acos(cos_1), top=False)
        return _Photon(x, y, layers.z1[0], dx * scale_1, dy * scale_1, cos_1, 0.0, 0)
    return _Photon(x, y, layers.z1[0], dx * scale_1, dy * scale_1, cos_1, transmitted, 1)


def step_size(photon: _Photon, layers: _Layers, rand: _Uniforms) -> float:
    """Length [cm] of the next step in a tissue layer: the unfinished part `sleft` if any,
    otherwise a fresh free path -ln(xi)/mut with xi in (0, 1]."""
    mut = layers.mut[photon.layer]
    if photon.sleft == 0.0:
        return -math.log(rand.next_open_zero()) / mut
    s = photon.sleft / mut
    photon.sleft = 0.0
    return s


def distance_to_face(photon: _Photon, layers: _Layers) -> float:
    """Distance [cm] along the direction to the face of the current layer the photon heads for
    (upper face if uz < 0, lower face if uz > 0, inf if uz == 0 or the layer is semi-infinite)."""
    if photon.uz > 0.0:
        return (layers.z1[photon.layer] - photon.z) / photon.uz
    if photon.uz < 0.0:
        return (layers.z0[photon.layer] - photon.z) / photon.uz
    return math.inf


def hop(photon: _Photon, s: float) -> None:
    """Move the photon `s` [cm] along its direction."""
    photon.x += s * photon.ux
    photon.y += s * photon.uy
    photon.z += s * photon.uz


def hop_to_face(photon: _Photon, distance: float, layers: _Layers) -> None:
    """Move the photon `distance` [cm] onto the face it heads for (z set exactly to the face)."""
    photon.x += distance * photon.ux
    photon.y += distance * photon.uy
    photon.z = layers.z1[photon.layer] if photon.uz > 0.0 else layers.z0[photon.layer]


def cross_or_not(photon: _Photon, layers: _Layers, rand: _Uniforms, tallies: _Tallies) -> None:
    """At a face: reflect with the Fresnel probability, otherwise transmit (MCML's all-or-none).

    Transmission into the ambient medium ends the photon, whose whole weight is tallied as diffuse
    reflectance (top) or transmittance (bottom) at the refracted exit angle. Transmission into
    another layer refracts the direction by Snell's law.
    """
    upward = photon.uz < 0.0
    here = photon.layer
    there = here - 1 if upward else here + 1
    n_here, n_there = layers.n[here], layers.index_of(there)
    r, cos_t = fresnel(n_here, n_there, abs(photon.uz))
    if rand.next_open_zero() <= r:
        photon.uz = -photon.uz
        return
    if there < 0 or there >= layers.count:
        tallies.escape(photon.w, photon.x, photon.y, math.acos(cos_t), top=upward)
        photon.w = 0.0
        photon.alive = False
        return
    scale = n_here / n_there
    photon.layer = there
    photon.ux *= scale
    photon.uy *= scale
    photon.uz = -cos_t if upward else cos_t


def drop(photon: _Photon, layers: _Layers, tallies: _Tallies) -> None:
    """Implicit capture: deposit dw = w mua / mut at the interaction point."""
    layer = photon.layer
    dw = photon.w * layers.mua[layer] / layers.mut[layer]
    photon.w -= dw
    tallies.absorb(dw, photon.x, photon.y, photon.z, layer)


def spin(photon: _Photon, g: float, rand: _Uniforms) -> None:
    """Deflect by a Henyey–Greenstein angle (anisotropy `g` [-]) and a uniform azimuth, with
    MCML's direction update (special case for a direction along ±z)."""
    cos_theta = sample_hg_cosine(g, rand.next())
    sin_theta = math.sqrt(1.0 - cos_theta * cos_theta)
    psi = 2.0 * math.pi * rand.next()
    cos_psi, sin_psi = math.cos(psi), math.sin(psi)
    ux, uy, uz = photon.ux, photon.uy, photon.uz
    if abs(uz) > COS_ZERO:
        photon.ux = sin_theta * cos_psi
        photon.uy = sin_theta * sin_psi
        photon.uz = cos_theta if uz > 0.0 else -cos_theta
    else:
        temp = math.sqrt(1.0 - uz * uz)
        photon.ux = sin_theta * (ux * uz * cos_psi - uy * sin_psi) / temp + ux * cos_theta
        photon.uy = sin_theta * (uy * uz * cos_psi + ux * sin_psi) / temp + uy * cos_theta
        photon.uz = -sin_theta * cos_psi * temp + uz * cos_theta


def roulette(photon: _Photon, chance: float, rand: _Uniforms) -> None:
    """Russian roulette: survive with probability `chance` and weight w / chance, or die.

    A photon whose weight is exactly 0 (fully absorbed in a non-scattering layer) has nothing left
    to carry and dies without drawing.
    """
    if photon.w == 0.0:
        photon.alive = False
    elif rand.next() < chance:
        photon.w /= chance
    else:
        photon.w = 0.0
        photon.alive = False


def hop_drop_spin(photon: _Photon, layers: _Layers, rand: _Uniforms, tallies: _Tallies) -> None:
    """One step of MCML's loop: in glass, hop to the face and cross or not; in tissue, either hit a
    face (carrying the unfinished step across as `sleft`) or hop, drop and spin."""
    layer = photon.layer
    distance = distance_to_face(photon, layers)
    if layers.is_glass(layer):
        if math.isinf(distance):  # uz == 0 in glass: never reaches a face (probability zero)
            photon.alive = False
            return
        hop_to_face(photon, distance, layers)
        cross_or_not(photon, layers, rand, tallies)
        return
    s = step_size(photon, layers, rand)
    if s > distance:
        hop_to_face(photon, distance, layers)
        photon.sleft = (s - distance) * layers.mut[layer]
        cross_or_not(photon, layers, rand, tallies)
    else:
        hop(photon, s)
        drop(photon, layers, tallies)
        spin(photon, layers.g[layer], rand)


def trace_photon(
    photon: _Photon, layers: _Layers, rand: _Uniforms, tallies: _Tallies, options: TraceOptions
) -> int:
    """Follow one launched photon until it escapes or dies; returns the number of steps taken."""
    steps = 0
    while photon.alive:
        hop_drop_spin(photon, layers, rand, tallies)
        steps += 1
        if photon.alive and photon.w < options.roulette_threshold:
            before = photon.w
            roulette(photon, options.roulette_chance, rand)
            tallies.roulette += photon.w - before
    return steps


# --------------------------------------------------------------------------------------------
# Entry point


def _halton(index: np.ndarray, base: int) -> np.ndarray:
    """Radical inverse of `index` in `base` (the Halton sequence), in [0, 1)."""
    result = np.zeros(index.shape, dtype=np.float64)
    i = index.astype(np.int64)
    f = 1.0 / base
    while np.any(i > 0):
        result += f * (i % base)
        i //= base
        f /= base
    return result


def _launch_points(scene: Scene, photons: int, rng: np.random.Generator, options: TraceOptions):
    """Surface points [cm] and incident directions for all photons, from the scene's source."""
    index = np.arange(photons, dtype=np.uint32)
    if options.launch == "halton":
        u = np.stack([_halton(index + 1, 2), _halton(index + 1, 3)], axis=-1)
    else:
        u = rng.random((photons, 2))
    xy, d = scene.source.launch(jnp.asarray(index), jnp.asarray(u, dtype=jnp.float64))
    return np.asarray(xy, dtype=np.float64), np.asarray(d, dtype=np.float64)


def trace_reference(
    scene: Scene | LayeredTissue,
    *,
    photons: int,
    seed: int,
    tallies: TallySpec = TallySpec(),
    options: TraceOptions = TraceOptions(),
    batches: int = 32,
) -> TraceResult:
    """Trace `photons` photons one at a time with MCML's rules (slow; the test oracle).

    Arguments:
    - `scene`: a `Scene` (tissue and source), or a `LayeredTissue` lit by MCML's normal pencil beam.
    - `photons`: number of photons launched, >= 1.
    - `seed`: integer seed of `numpy.random.default_rng`.
    - `tallies`: which resolved tallies to fill (others are None) and their grid (cm, rad).
    - `batches`: number of batches for the batch-means standard errors (an estimator independent of
      the fast tracer's per-photon moments).
    - `options`: roulette threshold and chance and the launch
      sampling ("random" or "halton": Halton bases 2 and 3 at index i + 1). Lanes, precision and
      step budgets do not apply: the reference always works in float64, one photon at a time.

    Returns a `TraceResult` normalised per launched photon as MCML does (rsp, rd, a, tt as
    fractions; rd_r [1/cm^2], rd_a [1/sr], a_z [1/cm], a_rz [1/cm^3], ...), with batch-means
    standard errors, and `roulette`, the net weight roulette created, so that
    rsp + rd + a + tt - roulette = 1 to rounding. `steps` counts every step (interaction or face);
    `outcome` is SUCCESSFUL; `path_stats` is not computed (None).
    """
    if isinstance(scene, LayeredTissue):
        scene = Scene(tissue=scene)
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a Scene or LayeredTissue, got {type(scene).__name__}")
    photons = check_positive_int("photons", photons)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed = {seed!r} must be an integer")
    layers = _Layers(scene.tissue)
    batches = min(check_positive_int("batches", batches), photons)
    rng = np.random.default_rng(seed)
    rand = _Uniforms(rng)
    xy, d = _launch_points(scene, photons, rng, options)

    record = _Tallies(tallies, layers, batches)
    batch_of = (np.arange(photons, dtype=np.int64) * batches) // photons
    batch_sizes = np.bincount(batch_of, minlength=batches).astype(np.float64)
    steps = 0
    for i in range(photons):
        record.batch = int(batch_of[i])
        photon = launch(float(xy[i, 0]), float(xy[i, 1]), tuple(d[i].tolist()), layers, record)
        steps += trace_photon(photon, layers, rand, record, options)

    out = record.finish(photons, batch_sizes)
    arrays = {k: jnp.asarray(np.asarray(v, dtype=np.float64)) for k, v in out.items()}
    return TraceResult(
        photons=photons,
        tallies=tallies,
        options=options,
        steps=jnp.asarray(steps, dtype=jnp.int64),
        outcome=Outcome.SUCCESSFUL,
        **arrays,
    )
