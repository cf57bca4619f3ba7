"""Next-event estimation to a camera inside the spectral lanes, and fluorescence by emission sites.

At every interaction (a photon arriving with band weights w_k at a point in medium m, from
direction w_in), the light it sends straight to the camera (`_camera.connect`) is scored into the
pixel the refracted ray lands in, for every band k at once:

    L_k += [ w_k (mus_k / mut_k) p_g(w_in . w_out)  +  sum_i w_i P[m, i, k] / (4 pi) ] e^(-tau_k) T G / Omega

The first term is the light scattered towards the camera (the collision estimator: w_k arrives,
a fraction mus/mut scatters, by the Henyey–Greenstein phase function per steradian). The second is
the expected fluorescence emitted there, isotropically: P[m, i, k] is the weight moved from band i
to band k per unit weight at an interaction (`SpectralTissue.conversion`), so summing it over every
interaction is what the sampled conversions would emit on average, without the sampling.

The camera lobe (`ImageSpec.lobe`). Under a forward-peaked phase function (tissue: g ~ 0.9)
p_g(w_in . w_out) spans a factor ~200 across directions, so a pixel's sum is ruled by the rare
photons that happen to fly towards the camera, and its variance is many times that of isotropic
scattering. At every scattering at P (arriving along w_P) the photon's next vertex A is sampled
along w ~ p_g(w_P . w); a second vertex A' is sampled along w' ~ q(w') = p_g(w' . c_P), the same
Henyey–Greenstein lobe around c_P, the connection's direction at P, at the same free-path
density (exp(-mut s)). Both estimate the light scattered towards the camera at the next vertex;
they are combined by the balance heuristic of multiple importance sampling (Veach 1997): A's
scattered light is weighted by p_g / (p_g + q), and A' scores

    W p_g(w_P . w') / (p_g(w_P . w') + q(w')) (mus / mut) p_g(w' . c_A') e^(-tau) T G / Omega,

where W is the weight leaving P. When w' lies near c the ratio p_g(w' . c_A') / q(w') is near 1:
the connection's peak cancels against the density that sampled it. Only vertices reached from P
without meeting a layer face or a region boundary take part (A' is dropped otherwise, and A then
keeps its full weight), so that both strategies cover the same paths. An emission site is
such a P too, its isotropic emission (1 / (4 pi)) in place of p_g(w_P . w). The weights are fixed at the
trace (derivatives by path replay are unchanged); p_g(w_P . w') is an explicit factor of A's
value, differentiated in g. Fluorescence emission (isotropic) is not weighted.

Fluorescence that scatters before it escapes needs traced fluorescence photons. With a camera the
tracer samples no conversion (the photon always scatters on with w mus/mut, its weight unaffected
by fluorescence). Instead each interaction is an emission site with probability

    q = min(1, rate * max_k E_k / u_k),     E_k = sum_i w_i P[m, i, k],

recorded with the power E / q it emits per band. u_k is the most any medium emits into band k per
unit weight of the source's spectrum (max over media and excitation bands of s_i P[m, i, k] / max s):
the strongest emitter of every band is sampled at `site_rate` sites per interaction of a photon of
launch weight, whatever the fluorophore's strength, and weaker or fainter light proportionally
less (importance by emitted power, band by band). The sites are then
traced as photons of their own (`EmissionSites`, `_image.trace_image`), `splits` isotropic
directions per site with the power divided: splitting at conversion. Every quantity is an unbiased
estimate of the analog one; the photon that excites keeps lighting the image after it excites,
which a sampled conversion would end.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._checks import check_positive_int, check_range
from ..scene import AbstractSource
from . import _adjoint, _physics as phys, _rng
from ._adjoint import FluenceGrid
from ._camera import Connection, PinholeCamera, connect, hg_intensity
from ._lanes import ALIVE, IDLE, KILLED, _expand, materialised
from ._lights import AreaLights
from ._records import segment_log_ratio
from ._spectral_state import SpectralConfig, _Sites
from ._spectral_weights import _sample_index, band_weights


class ImageSpec(eqx.Module):
    """What a spectral trace scores into a camera image (static: changing it recompiles).

    - `camera`: the `PinholeCamera` (its `batches` split the photons into independent images).
    - `sites`: capacity of the emission-site buffer (fluorescent scenes; 0 for none).
    - `site_rate`: emission sites per interaction of a launch-weight photon in the strongest
      emitter of a band (module docstring), in (0, 1].
    - `tangents`: K >= 0 directions in the tissue's coefficients along which the image is
      differentiated as it is scored (`trace_spectral(..., tangents=...)`; module docstring).
    - `from_sites`: the photons start at `EmissionSites` (set by `trace_spectral`).
    - `lobe`: score the camera lobe (module docstring) as well: lower variance where the phase
      function is forward-peaked, one more connection per interaction.
    - `grid`: a `FluenceGrid` (`_adjoint.py`): fluorescence is estimated from the camera instead of
      by emission sites. The lights' trace then tallies the excitation fluence into the grid and
      scores only the scattered light; a trace of `CameraPaths` (`from_camera`, set by
      `trace_spectral`) scores the fluorescence source the grid holds.
    - `lights`: `AreaLights` (`_lights.py`): a trace of `CameraPaths` scores the scattered light of
      these lights too (light sampling and the paths' own flights, by multiple importance sampling).
    - `scatter`: the lights' trace scores the scattered light by next-event estimation (default);
      False with a `grid`: it only tallies the fluence (the camera's paths score the scattered light).
    """

    camera: PinholeCamera = eqx.field(static=True)
    sites: int = eqx.field(static=True, default=0)
    site_rate: float = eqx.field(static=True, default=0.1)
    tangents: int = eqx.field(static=True, default=0)
    from_sites: bool = eqx.field(static=True, default=False)
    lobe: bool = eqx.field(static=True, default=True)
    grid: FluenceGrid | None = eqx.field(static=True, default=None)
    from_camera: bool = eqx.field(static=True, default=False)
    lights: AreaLights | None = eqx.field(static=True, default=None)
    scatter: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        if self.lights is not None and not isinstance(self.lights, AreaLights):
            raise TypeError(f"image.lights is a {type(self.lights).__name__}, not AreaLights")
        if not self.scatter and self.grid is None:
            raise ValueError("image: a trace that scores no scattered light (scatter=False) must tally a fluence grid")
        if self.grid is not None and not isinstance(self.grid, FluenceGrid):
            raise TypeError(f"image.grid is a {type(self.grid).__name__}, not a FluenceGrid")
        if self.from_camera and self.grid is None and self.lights is None:
            raise ValueError("image: paths from the camera need a fluence grid (image.grid) or lights (image.lights) to score")
        if not isinstance(self.camera, PinholeCamera):
            raise TypeError(f"image.camera is a {type(self.camera).__name__}, not a PinholeCamera")
        if not isinstance(self.sites, (int, np.integer)) or isinstance(self.sites, bool) or self.sites < 0:
            raise ValueError(f"image.sites = {self.sites!r}; allowed an integer >= 0 (buffer capacity)")
        check_range("image.site_rate", self.site_rate, unit="sites per interaction", low=0.0, high=1.0, low_open=True)
        if not isinstance(self.tangents, (int, np.integer)) or isinstance(self.tangents, bool) or not 0 <= self.tangents <= 64:
            raise ValueError(f"image.tangents = {self.tangents!r}; allowed an integer 0 .. 64")


class EmissionSites(AbstractSource):
    """Fluorescence emission sites as a source inside the tissue: each site emits `splits` photons
    isotropically, each with 1/splits of its power (`power` per active band, the traced slots).

    Fields (arrays, not differentiable: positions and powers of one trace): `position` [n, 3] (x, y,
    absolute depth) cm, `layer`, `medium` [n] int, `power` [n, slots], `origin` [n] int (the launch
    each descends from: its image batch), `tangent` [n, slots, K] (the power's derivative along the
    trace's tangent directions, or None); `splits` static. Photon i starts at site i // splits."""

    position: Float[Array, "n 3"]
    layer: Int[Array, " n"]
    medium: Int[Array, " n"]
    power: Float[Array, "n slots"]
    origin: Int[Array, " n"]
    tangent: Float[Array, "n slots k"] | None = None
    splits: int = eqx.field(static=True, default=1)

    def __check_init__(self):
        check_positive_int("sites.splits", self.splits, high=1024)

    @property
    def count(self) -> int:
        return int(self.position.shape[0])

    def padded(self, rows: int, splits: int) -> "EmissionSites":
        """The same sites in arrays of `rows` >= count rows (zero power beyond: never launched), traced
        `splits` times each: arrays of a few sizes share the tracer's compilation."""
        extra = rows - self.count

        def pad(a):
            a = np.asarray(a)
            return np.concatenate([a, np.zeros((extra, *a.shape[1:]), a.dtype)])

        return EmissionSites(position=pad(self.position), layer=pad(self.layer), medium=pad(self.medium),
                             power=pad(self.power), origin=pad(self.origin),
                             tangent=None if self.tangent is None else pad(self.tangent), splits=splits)

    def launch(self, index, u):  # pragma: no cover - sites are launched by `refill_sites`
        raise TypeError("EmissionSites launch inside the tissue (refill_sites), not from the surface")


def slot_index(config: SpectralConfig, band: Array) -> Array:
    """Per band mode: the image slot (position in `active`) of band indices."""
    table = np.full(config.num_bands, 0, np.int32)
    table[np.asarray(config.active)] = np.arange(config.slots)
    return jnp.asarray(table)[band]


def _active_props(mua, mus, g, conv, config: SpectralConfig):
    """The flat medium tables as [media, slots] (and conv [media, slots, slots]) of the active bands."""
    nb, act = config.num_bands, jnp.asarray(config.active)

    def table(a):
        return a.reshape(-1, nb)[:, act]

    c = None if conv is None else conv.reshape(config.num_media, nb, nb)[:, act][:, :, act]
    return table(mua), table(mus), table(g), c


class _Vertex(NamedTuple):
    """What `_values` needs of the points a step scores (lanes), fixed at the trace.

    `w0` [lanes, slots] the traced band weights arriving; `path`, `hits`, `score` [lanes, media]
    the path statistics since launch or the emission site (`path` None without tangents); `med`
    the medium; `cos` the cosine between the arriving direction and the connection; `lengths`,
    `factor` the connection's (`Connection`); `mis` [lanes] the weight of the scattered light (the
    lane's `mis`: module docstring), or None for 1; `pre` (cos_p, density) for a vertex sampled
    towards the camera: its scattered light is weighted by p_g(cos_p) / density instead (cos_p None:
    by 1 / (4 pi density), the vertex following an isotropic emission)."""

    w0: Array
    path: Array | None
    hits: Array | None
    score: Array | None
    med: Array
    cos: Array
    lengths: Array
    factor: Array
    mis: Array | None = None
    pre: tuple | None = None


def _values(props, spectrum_change, v: _Vertex, config: SpectralConfig):
    """The light one interaction per lane scores into the camera, per band, and the fluorescence it
    emits (module docstring), as functions of the media's coefficients `props` (mua, mus, g [media,
    slots], conv [media, slots, slots] or None) and of `spectrum_change` [lanes, slots], the relative
    change of the photon's spectrum (0 at the trace): at the traced coefficients both equal the traced
    values, and their derivatives there are the likelihood-ratio derivatives (jvp along tangents).
    Returns (value [lanes, slots], emitted E or None)."""
    mua, mus, g, conv = props
    med = v.med
    if v.path is not None:
        props0 = jax.tree.map(jax.lax.stop_gradient, (mua, mus, g))
        w = v.w0 * jnp.exp(segment_log_ratio(v.path, v.hits, v.score, (mua, mus, g), props0)) * (1.0 + spectrum_change)
    else:
        w = v.w0
    mut = mua + mus
    # The interaction density mut at the vertex is the sampling's (held at the trace): scattering
    # there is mus / mut0 and conversion P mut / mut0 (P is per interaction: mu_conv / mut).
    mut0 = jax.lax.stop_gradient(mut)
    inverse0 = jnp.where(mut0 > 0, 1.0 / jnp.where(mut0 > 0, mut0, 1.0), 0.0)
    phase = hg_intensity(g[med], v.cos[:, None])
    if v.pre is not None:
        cos_p, density = v.pre
        before = 1.0 / (4.0 * math.pi) if cos_p is None else hg_intensity(g[med], cos_p[:, None])
        phase = phase * before / density[:, None]
    elif v.mis is not None:
        phase = phase * v.mis[:, None]
    intensity = w * mus[med] * inverse0[med] * phase
    emitted = None
    if conv is not None:
        conv = conv * (mut * inverse0)[:, :, None]
        emitted = w @ conv[0]
        for m in range(1, config.num_media):
            emitted = jnp.where((med == m)[:, None], w @ conv[m], emitted)
        intensity = intensity + emitted * (1.0 / (4.0 * math.pi))
    value = intensity * jnp.exp(-(v.lengths @ mut)) * v.factor[:, None]
    return value, emitted


def _arriving(lanes, w, path, hits, medium, config: SpectralConfig, mask, med):
    """The traced band weights [lanes, slots] of lanes arriving with carrier weight `w` and path
    statistics (path, hits) at an interaction in medium `med`, each band's under its own interaction
    density (`band_weights(arrival=...)`: `_values` scatters mus_k / mut_k of it); 0 outside `mask`."""
    if config.shared:
        w0 = band_weights(w, lanes.spectrum, path, hits, lanes.band, medium, arrival=med)
    else:
        w0 = jax.nn.one_hot(slot_index(config, lanes.band), config.slots, dtype=w.dtype) * w[:, None]
    return jnp.where(mask[:, None], w0, 0.0)


def _deposit(acc, lanes, medium, config: SpectralConfig, vertex: _Vertex, conn: Connection, mask, fluorescence: bool):
    """Add the vertices' values (and, with tangents, their derivatives) into `acc.image`.
    Returns (acc, emitted, demitted): the expected emission, when `fluorescence`."""
    cam = config.image.camera
    k = config.tangents
    props = _active_props(medium.mua, medium.mus, medium.g, medium.conv if fluorescence else None, config)
    tangents = change = None
    if k:
        (dmua, dmus, dg), dconv = medium.dprops
        tangents = jax.vmap(lambda a, b, c, d: _active_props(a, b, c, d if fluorescence else None, config))(
            dmua, dmus, dg, dconv)
        change = jnp.zeros((k,) + vertex.w0.shape, vertex.w0.dtype) if lanes.dlog_s is None else jnp.moveaxis(lanes.dlog_s, -1, 0)

    def rows(vertex, props, tangents, change):
        # the image rows [lanes, (1 + K) slots] (values, then the derivatives), emitted, its derivatives
        no_change = jnp.zeros_like(vertex.w0)
        values = lambda p, c: _values(p, c, vertex, config)  # noqa: E731
        if not k:
            value, emitted = values(props, no_change)
            return value, emitted, None
        (value, emitted), (dvalue, demitted) = jax.vmap(
            lambda t, c: jax.jvp(values, (props, no_change), (t, c)), out_axes=(None, 0))(tangents, change)
        return jnp.concatenate([value, jnp.moveaxis(dvalue, 0, 1).reshape(value.shape[0], -1)], axis=1), emitted, demitted

    row_values, emitted, demitted = materialised(rows, mask, vertex, props, tangents, change)
    batch = (lanes.origin % cam.batches).astype(jnp.int32)
    row = jnp.where(mask & conn.valid, batch * cam.pixels + conn.pixel, cam.batches * cam.pixels)
    return acc._replace(image=acc.image.at[row].add(row_values.astype(jnp.float64), mode="drop")), emitted, demitted


def score(acc, lanes, medium, tissue, config: SpectralConfig, *, interact, x, y, z_abs, med, path_in, xi):
    """Score the camera's next-event estimate of this step's interactions into `acc.image` (and,
    with tangents, its derivatives), and sample emission sites into `acc.sites` (fluorescent
    scenes). `lanes` is the photon arriving (weight, spectrum, direction, hits and score before this
    interaction); `path_in` its path lengths with this hop; `xi` a uniform per lane for the site
    decision. Returns (acc, the connection's direction at the points: the camera lobe's axis)."""
    cam = config.image.camera
    w0 = _arriving(lanes, lanes.w, path_in, lanes.hits, medium, config, interact, med)
    if not config.image.scatter:  # the lights' pass of estimates from the camera: the fluence only
        return _adjoint.tally(acc, lanes, medium, config, w0, interact, x, y, z_abs, med, path_in), None
    conn = connect(x, y, z_abs, lanes.layer, tissue, medium.n_ext, medium.z0, medium.thickness, cam, medium.solid_angle)
    cos = lanes.ux * conn.direction[0] + lanes.uy * conn.direction[1] + lanes.uz * conn.direction[2]
    vertex = _Vertex(w0=w0, path=path_in if config.tangents else None, hits=lanes.hits, score=lanes.score, med=med,
                     cos=cos, lengths=conn.lengths, factor=conn.factor, mis=lanes.mis)
    acc, emitted, demitted = _deposit(acc, lanes, medium, config, vertex, conn, interact, config.sites)
    if config.fluence:
        acc = _adjoint.tally(acc, lanes, medium, config, w0, interact, x, y, z_abs, med, path_in)
    if config.sites:
        acc = acc._replace(**_record_sites(acc, lanes, medium, config, w0, emitted, demitted, interact, x, y, z_abs, med, xi))
    return acc, conn.direction


def score_lobe(acc, lanes, medium, tissue, config: SpectralConfig, *, scatter, x, y, z, z_abs, med, g, mut, w, path, hits,
               axis, new_dir, xi, emission=False):
    """The camera lobe (module docstring): for lanes that `scatter` at (x, y, z) (z below the layer's
    top face, z_abs absolute) in medium `med`, with Henyey–Greenstein `g` and interaction
    coefficient `mut` of the carrier, leaving with weight `w` and path statistics (path, hits), in
    the sampled direction `new_dir` (the lanes' direction arriving is `lanes.ux, uy, uz`): score a
    next vertex sampled around `axis` (the connection's direction here), and return (acc, mis), the
    weight of the scattered light at the next vertex the photon itself reaches, if it reaches it
    without meeting a face or a region boundary. `xi`: three uniforms per lane. With `emission`
    the lanes start there with an isotropic direction (an emission site) instead of scattering."""
    dtype = x.dtype
    ax, ay, az = axis
    iso = jnp.full_like(x, 1.0 / (4.0 * math.pi))
    p_new = iso if emission else hg_intensity(g, lanes.ux * new_dir[0] + lanes.uy * new_dir[1] + lanes.uz * new_dir[2])
    q_new = hg_intensity(g, ax * new_dir[0] + ay * new_dir[1] + az * new_dir[2])
    mis = p_new / (p_new + q_new)
    # the next vertex, drawn around the axis and at the photon's own free-path density
    cos_v = phys.sample_hg_cos(g, xi[0])
    vx, vy, vz = phys.spin(ax, ay, az, cos_v, xi[1])
    s = -jnp.log(xi[2]) / jnp.where(mut > 0, mut, 1.0)
    cos_p = lanes.ux * vx + lanes.uy * vy + lanes.uz * vz
    density = (iso if emission else hg_intensity(g, cos_p)) + hg_intensity(g, cos_v)
    zv = z + vz * s
    direct = scatter & (mut > 0) & (zv > 0) & (zv < medium.thickness[lanes.layer])
    if tissue.regions:
        p = jnp.stack([x, y, z_abs])
        u = jnp.stack([vx, vy, vz])
        for region in tissue.regions:
            t_in, t_out = region.distances(p, u)
            crosses = ((t_in > 0) & (t_in < s)) | ((t_out > 0) & (t_out < s))
            direct = direct & ~crosses
    path_v = None
    if path is not None:
        onehot = (med[:, None] == jnp.arange(config.num_media, dtype=jnp.int32)[None, :]).astype(dtype)
        path_v = path + onehot * s[:, None]
    xv, yv, zv_abs = x + vx * s, y + vy * s, z_abs + vz * s
    conn = connect(xv, yv, zv_abs, lanes.layer, tissue, medium.n_ext, medium.z0, medium.thickness, config.image.camera,
                   medium.solid_angle)
    w0 = _arriving(lanes, w, path_v, hits, medium, config, direct, med)
    cos = vx * conn.direction[0] + vy * conn.direction[1] + vz * conn.direction[2]
    vertex = _Vertex(w0=w0, path=path_v if config.tangents else None, hits=hits, score=lanes.score, med=med, cos=cos,
                     lengths=conn.lengths, factor=conn.factor, pre=(None if emission else cos_p, density))
    acc, _, _ = _deposit(acc, lanes, medium, config, vertex, conn, direct, False)
    return acc, mis


def _record_sites(acc, lanes, medium, config: SpectralConfig, w, emitted, demitted, interact, x, y, z_abs, med, xi) -> dict:
    """Sample emission sites (module docstring) into the buffer, and book the expected conversions."""
    total = jnp.sum(emitted, axis=1)
    units = jax.lax.stop_gradient(site_units(medium, config))
    strength = jnp.max(emitted / units, axis=1)
    q = jnp.minimum(1.0, config.image.site_rate * strength)
    take = interact & (total > 0) & (xi < q)
    inverse = 1.0 / jnp.where(q > 0, q, 1.0)
    tangent = None if demitted is None else jnp.moveaxis(demitted, 0, -1) * inverse[:, None, None]
    sites = _append_sites(acc.sites, take, position=jnp.stack([x, y, z_abs], -1), layer=lanes.layer, medium=med,
                          power=emitted * inverse[:, None], origin=lanes.origin, tangent=tangent)
    # the weight converted out of each band (expected), as first conversions or re-conversions
    nb, act = config.num_bands, jnp.asarray(config.active)
    psum = medium.psum.reshape(-1, nb)[:, act][med]
    out = (w * psum).astype(jnp.float64)
    again = lanes.converted[:, None]
    flux = acc.flux.at[act, 2].add(jnp.where(again, 0.0, out).sum(0)).at[act, 3].add(jnp.where(again, out, 0.0).sum(0))
    return {"sites": sites, "flux": flux}


def site_units(medium, config: SpectralConfig) -> Array:
    """u [slots]: the most any medium emits into each band per unit weight of the source's spectrum,
    max over media and excitation bands i of s_i P[m, i, k] / max s (1 where nothing emits)."""
    nb, act = config.num_bands, jnp.asarray(config.active)
    conv = medium.conv.reshape(config.num_media, nb, nb)[:, act][:, :, act]
    source = medium.power[act] / jnp.max(medium.power[act])
    # light converted once can convert again: its own bands count as sources too
    carried = jnp.maximum(source, (conv.max((0, 1)) > 0).astype(source.dtype))
    u = jnp.max(conv * carried[None, :, None], axis=(0, 1))
    return jnp.where(u > 0, u, 1.0)


def _append_sites(buf: _Sites, mask, **rows) -> _Sites:
    cap = buf.position.shape[0]
    slot = buf.count + jnp.cumsum(mask.astype(jnp.int64)) - 1
    idx = jnp.where(mask & (slot < cap), slot, cap)
    new = {k: getattr(buf, k).at[idx].set(v.astype(getattr(buf, k).dtype), mode="drop") for k, v in rows.items()
           if v is not None}
    added = mask.astype(jnp.int64).sum()
    fits = jnp.minimum(added, cap - buf.count)
    return buf._replace(count=buf.count + fits, overflow=buf.overflow + added - fits, **new)


def refill_sites(lanes, acc, medium, sites: EmissionSites, words, end, config: SpectralConfig, tissue):
    """Launch photons next_pid, ... (below `end`) from emission sites into lanes that are not alive:
    photon i from site i // splits, an isotropic direction, 1/splits of the site's power, a carrier
    band (shared) or its band (per band) drawn from the site's spectrum; fluorescence light. With
    the camera lobe, the emission is its first strategy and a vertex around the camera's direction
    is scored (`score_lobe`)."""
    dtype = lanes.x.dtype
    free = lanes.status != ALIVE
    new_pid = acc.next_pid + jnp.cumsum(free.astype(jnp.int64)) - 1
    start = free & (new_pid < end)
    pid = jnp.where(start, new_pid, lanes.pid)
    rng = _rng.seed_streams(words, pid.astype(jnp.uint32))
    site = jnp.clip(pid // sites.splits, 0, sites.position.shape[0] - 1)
    pos = sites.position[site].astype(dtype)
    layer = sites.layer[site].astype(jnp.int32)
    power = sites.power[site].astype(dtype) / sites.splits  # [lanes, slots]
    dlog_s = None
    if lanes.dlog_s is not None:  # the relative derivative of each band's power along the tangents
        p0 = sites.power[site].astype(dtype)
        dlog_s = sites.tangent[site].astype(dtype) / jnp.where(p0 > 0, p0, 1.0)[:, :, None]
    xi_a, rng = _rng.next_uniform(rng, dtype)
    xi_b, rng = _rng.next_uniform(rng, dtype)
    xi_c, rng = _rng.next_uniform(rng, dtype)
    cos_t = 2.0 * xi_a - 1.0
    sin_t = jnp.sqrt(jnp.maximum(1.0 - cos_t * cos_t, 0.0))
    psi = 2.0 * jnp.pi * xi_b
    total = jnp.sum(power, axis=1)
    pick = _sample_index(jnp.cumsum(power, axis=1), xi_c)
    if config.shared:
        peak = jnp.max(power, axis=1)
        w = peak
        spectrum = power / jnp.where(peak > 0, peak, 1.0)[:, None]
        band = pick
    else:
        w = total
        spectrum = None
        band = jnp.asarray(config.active, jnp.int32)[pick]
    zeros = jnp.zeros_like(pos[:, 0])
    new = lanes._replace(
        x=pos[:, 0], y=pos[:, 1], z=pos[:, 2] - medium.z0[layer], ux=sin_t * jnp.cos(psi), uy=sin_t * jnp.sin(psi),
        uz=cos_t, w=w, spectrum=spectrum,
        path=None if lanes.path is None else jnp.zeros_like(lanes.path),
        hits=None if lanes.hits is None else jnp.zeros_like(lanes.hits),
        sleft=zeros, layer=layer, medium=sites.medium[site].astype(jnp.int32), band=band.astype(jnp.int32),
        converted=jnp.ones(pos.shape[:1], bool), status=jnp.where(total > 0, ALIVE, KILLED).astype(jnp.int32),
        pid=pid, rng=rng, heat=zeros, roulette=zeros, steps=jnp.zeros(pos.shape[:1], jnp.int32),
        origin=sites.origin[site].astype(jnp.int64), dlog_s=dlog_s, mis=None if lanes.mis is None else jnp.ones_like(zeros),
    )
    if config.image.lobe:
        new, acc = _lobe_from_sites(new, acc, medium, config, tissue, start & (total > 0))
    lanes = jax.tree.map(lambda a, b: jnp.where(_expand(start, a), a, b), new, lanes)
    lanes = lanes._replace(status=jnp.where(free & ~start, IDLE, lanes.status))
    emitted = jnp.where(start[:, None], power, 0.0).astype(jnp.float64).sum(0)
    act = jnp.asarray(config.active)
    acc = acc._replace(next_pid=jnp.minimum(acc.next_pid + free.astype(jnp.int64).sum(), end),
                       flux=acc.flux.at[act, 1].add(emitted))
    return lanes, acc


def _lobe_from_sites(new, acc, medium, config: SpectralConfig, tissue, start):
    """The camera lobe at emission sites: the photons `new` (just started) emit isotropically; score
    the vertex drawn around the camera's direction and set their `mis` (`score_lobe`)."""
    z_abs = new.z + medium.z0[new.layer]
    conn = connect(new.x, new.y, z_abs, new.layer, tissue, medium.n_ext, medium.z0, medium.thickness, config.image.camera,
                   medium.solid_angle)
    carrier = jnp.asarray(config.active, jnp.int32)[new.band] if config.shared else new.band
    flat = new.medium * config.num_bands + carrier
    xi = []
    rng = new.rng
    for _ in range(3):
        u, rng = _rng.next_uniform(rng, new.x.dtype)
        xi.append(u)
    acc, mis = score_lobe(acc, new, medium, tissue, config, scatter=start, x=new.x, y=new.y, z=new.z, z_abs=z_abs,
                          med=new.medium, g=medium.g[flat], mut=medium.mua[flat] + medium.mus[flat], w=new.w, path=new.path,
                          hits=new.hits, axis=conn.direction, new_dir=(new.ux, new.uy, new.uz), xi=xi, emission=True)
    return new._replace(mis=mis, rng=rng), acc
