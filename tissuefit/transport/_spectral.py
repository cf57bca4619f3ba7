"""The multi-spectral tracer with fluorescence: `trace_spectral(scene, ...)` → `SpectralResult`.

It drives the lanes of `_spectral_lanes.py` with the same loop, sharding, chunking and
checkpointing as the single-band `trace` (`_trace.run_lanes`). What is compiled follows from the
static scene: no fluorophore, no conversion code; bands with no source power and no emission
reaching them carry no weight (shared mode: not even a slot); no record buffers unless asked for.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._checks import check_positive_int, check_range, checked_parameters, is_concrete
from .._outcome import Outcome
from .._setup import float64
from ..scene import BandGrid, SpectralScene
from ._adjoint import POWER_FLOOR, CameraPaths, fluence_of
from ._config import TraceOptions
from ._nee import EmissionSites, ImageSpec, refill_sites
from ._records import REPLAY_FIELDS, PhotonRecords, RecordSpec
from ._spectral_lanes import harvest, refill, step
from ._spectral_state import SpectralConfig, idle_lanes, medium_arrays, zeros_acc
from ._spectral_weights import band_weights
from ._trace import MAX_PHOTONS, TAIL_SHRINK, TraceState, run_lanes

Mode = Literal["auto", "per_band", "shared"]


class SpectralOptions(eqx.Module):
    """How the spectrum is carried (static).

    - `mode`: "per_band" (a photon carries one band at a time), "shared" (every photon carries all
      active bands along one path, reweighted by likelihood ratios; needs g equal across bands in
      each medium, and no voxel grid) or "auto" (default): shared wherever it can serve the scene
      (one path serves all bands at the cost of one; on blood spectra it measured 4-11x more
      efficient per band than per-band tracing: experiments/spectral/RESULTS.md), else per band.
    - `conversion_boost`: b >= 1; the odds of converting at an interaction are b times the analog
      odds, q = b q_a / (1 + (b - 1) q_a), with both branches' weights divided by their sampling
      probabilities (unbiased; more fluorescence photons per launched photon). The odds form keeps
      q < 1 wherever scattering is possible: a plain cap min(1, b q_a) would never sample the
      scattering branch where b q_a >= 1 and lose that light (measured: a marched fluorescence
      image 30% low before this form). 1 keeps every photon's energy exactly conserved.
    """

    mode: Mode = eqx.field(static=True, default="auto")
    conversion_boost: float = eqx.field(static=True, default=1.0)

    def __check_init__(self):
        if self.mode not in ("auto", "per_band", "shared"):
            raise ValueError(f"spectral.mode = {self.mode!r}; allowed 'auto', 'per_band' or 'shared'")
        check_range("spectral.conversion_boost", self.conversion_boost, unit="-", low=1.0)


class SpectralResult(eqx.Module):
    """Per-band tallies of a spectral trace, normalised per launched photon (numpy, float64).

    Fractions of the launched power (the source's in-grid power is 1), per band [bands]:
    - `launched`: weight entering the tissue in each band (1 - Rsp of the source's band power;
      per_band: a Monte Carlo estimate, shared: exact); `rsp`: specular reflection per band.
    - `rd`, `tt`: escaping through the top / bottom in each band (fluorescence included);
      `rd_fluor`, `tt_fluor`: the part carried by converted (fluorescence) photons.
    - `a`: absorbed as heat in each band (by tissue and by fluorophores, less what they re-emit);
      `a_fluor`: the part absorbed from fluorescence light.
    - `emitted`: fluorescence emitted into each band; `converted`: weight converted out of each
      band (first conversions), `reconverted`: conversions of fluorescence light.
    - `roulette`: net weight created by roulette per band (zero-mean); `roulette_fluor` its part
      on converted photons.
    - `rd_stderr`, `tt_stderr`, `rd_fluor_stderr`, `tt_fluor_stderr`: standard errors from
      per-photon moments.
    Bookkeeping: per band, launched + emitted = rd + tt + a + converted + reconverted - roulette,
    to rounding with conversion_boost = 1 in per_band mode or with equal properties across bands
    (every photon's weight is conserved), in expectation otherwise (boosted splits and likelihood
    ratios create and destroy weight with zero mean).
    Shared mode resolves weights per band only where light leaves or converts: there `a` and
    `a_fluor` are what the balance leaves (unbiased) and `roulette` is not resolved (zeros).
    Totals over bands: `rd_total`, `tt_total` (with per-photon standard errors), `a_total`, `rsp_total`.
    `surface_records`, `volume_records`: `PhotonRecords` or None when not requested.
    With `image=ImageSpec(...)`: `image` [batches, bands, H, W], the camera's next-event radiance
    per launched photon [1/(cm^2 sr)] of each batch of photons (their mean is the image; their spread
    its Monte Carlo noise), and in fluorescent scenes `sites`, the emission sites sampled
    (`EmissionSites`, powers per launched photon of this trace times its photon count: raw weights),
    `sites_overflow` the sites that did not fit (their light is missing: retrace with more room).
    With `tangents`: `image_tangents` [batches, K, bands, H, W], the image's derivative along each.
    With `image.grid` (the lights' pass of fluorescence from the camera, `_adjoint.py`): `fluence`
    [batches, excitation bands, voxels], the excitation fluence per unit launched power [1/cm^2],
    and with tangents `fluence_tangents` [K, batches, excitation bands, voxels] its derivatives.
    `mode`: the mode used; `active`: the bands traced; `photons`, `steps`, `outcome` (`tissuefit.Outcome`).
    """

    photons: int = eqx.field(static=True)
    bands: BandGrid = eqx.field(static=True)
    mode: str = eqx.field(static=True)
    active: tuple[int, ...] = eqx.field(static=True)
    launched: Float[Array, " bands"]
    rsp: Float[Array, " bands"]
    rd: Float[Array, " bands"]
    tt: Float[Array, " bands"]
    rd_fluor: Float[Array, " bands"]
    tt_fluor: Float[Array, " bands"]
    rd_stderr: Float[Array, " bands"]
    tt_stderr: Float[Array, " bands"]
    rd_fluor_stderr: Float[Array, " bands"]
    tt_fluor_stderr: Float[Array, " bands"]
    a: Float[Array, " bands"]
    a_fluor: Float[Array, " bands"]
    emitted: Float[Array, " bands"]
    converted: Float[Array, " bands"]
    reconverted: Float[Array, " bands"]
    roulette: Float[Array, " bands"]
    roulette_fluor: Float[Array, " bands"]
    rsp_total: Float[Array, ""]
    rd_total: Float[Array, ""]
    a_total: Float[Array, ""]
    tt_total: Float[Array, ""]
    rd_total_stderr: Float[Array, ""]
    tt_total_stderr: Float[Array, ""]
    steps: Array
    outcome: Outcome = eqx.field(static=True)
    surface_records: PhotonRecords | None = None
    volume_records: PhotonRecords | None = None
    image: np.ndarray | None = None
    image_tangents: np.ndarray | None = None
    sites: EmissionSites | None = None
    sites_overflow: int = 0
    fluence: np.ndarray | None = None
    fluence_tangents: np.ndarray | None = None

    @property
    def wavelengths(self) -> np.ndarray:
        """Band centres [nm]."""
        return self.bands.wavelengths


def _active_properties(scene: SpectralScene, active: tuple[int, ...]):
    mua, mus, g = scene.tissue.properties()
    if not all(is_concrete(t) for t in (mua, mus, g)):
        return None
    idx = np.asarray(active)
    return tuple(np.asarray(t)[:, idx] for t in (mua, mus, g))


def _shared_ok(props) -> str | None:
    """Why shared paths cannot serve these properties, or None."""
    mua, mus, g = props
    mut = mua + mus
    for name, values in (("mua + mus", mut), ("mus", mus)):
        mixed = np.nonzero((values > 0).any(1) & ~(values > 0).all(1))[0]
        if mixed.size:
            return f"medium {int(mixed[0])} has {name} = 0 1/cm in some bands and > 0 in others"
    uneven = np.nonzero(np.ptp(g, axis=1) > 0)[0]
    if uneven.size:
        return f"medium {int(uneven[0])} has g differing between bands ({g[uneven[0]].min():g} .. {g[uneven[0]].max():g})"
    return None


def resolve_config(scene: SpectralScene, options: TraceOptions, spectral: SpectralOptions, records: RecordSpec,
                   image: ImageSpec | None = None) -> SpectralConfig:
    """The static configuration of a spectral trace, decided in Python from the scene."""
    active = scene.active_bands()
    fluorescent = scene.tissue.fluorescent
    if image is not None and (image.grid is not None or image.from_camera):
        # estimates from the camera (`_adjoint.py`): neither pass samples conversions. The
        # lights' pass carries the lit bands; the camera's paths the bands they score.
        fluorescent = False
        if image.from_camera:
            active = tuple(scene.source.bands)
        else:
            power = np.asarray(scene.band_power())
            active = tuple(int(b) for b in np.nonzero((power > 0) & (power >= POWER_FLOOR * power.max()))[0])
            missing = sorted(set(image.grid.bands) - set(active))
            if missing:
                raise ValueError(f"image.grid.bands: bands {missing} carry no source power (lit: {list(active)})")
    props = _active_properties(scene, active)
    mode = spectral.mode
    voxels = any(r.num_media > 1 for r in scene.tissue.regions)
    if mode == "auto":
        # Shared paths whenever they can serve the scene: measured 4-11x more efficient per band
        # than per-band tracing even for blood spectra (mut differing by 67 % across bands;
        # experiments/spectral/RESULTS.md).
        shareable = props is not None and not voxels and _shared_ok(props) is None
        mode = "shared" if shareable else "per_band"
    elif mode == "shared":
        if voxels:
            raise ValueError("spectral.mode = 'shared': voxel grids are traced per band only (use 'per_band' or 'auto')")
        if props is None:
            raise ValueError("spectral.mode = 'shared' needs concrete optical properties to check; trace outside jit or use 'per_band'")
        why = _shared_ok(props)
        if why is not None:
            raise ValueError(f"spectral.mode = 'shared': {why}; shared paths cannot serve that. Use mode 'per_band'.")
    if image is not None:
        if voxels:
            raise ValueError("image: next-event estimation does not support voxel grids (their media vary along the "
                             "connection to the camera); render them with estimator='march'")
        if records.any and scene.tissue.fluorescent:
            raise ValueError("image: a fluorescent trace scoring a camera image keeps no photon records (its "
                             "conversions are emission sites, not converted photons)")
        if isinstance(scene.source, EmissionSites) and scene.source.power.shape[1] != len(active):
            raise ValueError(f"image: the emission sites carry {scene.source.power.shape[1]} bands, the scene's "
                             f"active bands are {len(active)}")
    return SpectralConfig(
        mode=mode, num_bands=scene.tissue.bands.num_bands, active=active, fluorescent=fluorescent,
        num_layers=scene.tissue.num_layers, num_media=scene.tissue.num_media, boost=float(spectral.conversion_boost),
        records=records, options=options, image=image,
    )


class _Inputs(eqx.Module):
    """What the spectral lanes read: the scene, and the tangent tissues an image is differentiated along."""

    scene: SpectralScene
    tangents: tuple = ()


class SpectralKernel(eqx.Module):
    """The spectral lanes behind `_trace._loop`'s kernel interface."""

    config: SpectralConfig = eqx.field(static=True)

    # a spectral step (every band's weight, camera connections, path statistics) is costly enough that
    # the tail's lanes are compacted (`_trace.TAIL_SHRINK`)
    tail_shrink = TAIL_SHRINK

    @property
    def options(self) -> TraceOptions:
        return self.config.options

    def checked(self, inputs):
        """`inputs` with the tissue's parameters checked (not the tangents: directions may be negative)."""
        tissue = checked_parameters(inputs.scene.tissue, "scene.tissue")
        return eqx.tree_at(lambda i: i.scene.tissue, inputs, tissue)

    def medium(self, inputs):
        return medium_arrays(inputs.scene, self.config, jnp.dtype(self.options.precision), inputs.tangents)

    def refill(self, lanes, acc, medium, inputs, words, end):
        if self.config.launch_sites:
            return refill_sites(lanes, acc, medium, inputs.scene.source, words, end, self.config, inputs.scene.tissue)
        return refill(lanes, acc, medium, inputs.scene, words, end, self.config)

    def step(self, lanes, acc, medium, inputs):
        return step(lanes, acc, medium, inputs.scene.tissue, self.config)

    def harvest(self, lanes, acc, medium):
        return harvest(lanes, acc, medium, self.config)



@float64
def trace_spectral(
    scene: SpectralScene,
    *,
    key: Array,
    photons: int,
    options: TraceOptions = TraceOptions(),
    spectral: SpectralOptions = SpectralOptions(),
    records: RecordSpec = RecordSpec(),
    chunks: int = 1,
    progress=None,
    devices=None,
    resume: TraceState | None = None,
    on_chunk=None,
    image: ImageSpec | None = None,
    tangents: tuple = (),
) -> SpectralResult:
    """Trace `photons` photons of the scene's source spectrum through a `SpectralScene`.

    Arguments as for `trace` (`key` keyword-only; `options` lanes, precision, launch, roulette,
    budget; `chunks`, `progress`, `devices`, `resume`, `on_chunk`), plus:
    - `spectral`: `SpectralOptions` (per-band or shared paths, conversion boost);
    - `records`: `RecordSpec`, capacities of the surface and volume photon records (default none).
    - `image`: `ImageSpec`, a camera to score next-event estimates into (default none; `_nee.py`).
      The scene's source may then be `EmissionSites` (fluorescence light from a previous trace).
    - `tangents`: with an image, tissues shaped like `scene.tissue` whose leaves are directions in
      its coefficients (e.g. `jax.jvp` of a parametrised tissue): the image's derivative along each
      is scored too, by path replay of every scored contribution (`SpectralResult.image_tangents`).
    Returns a `SpectralResult`: per-band tallies normalised per launched photon, with records.
    """
    photons = check_positive_int("photons", photons, high=MAX_PHOTONS)
    chunks = check_positive_int("chunks", chunks, high=photons)
    if not isinstance(scene, SpectralScene):
        raise TypeError(f"scene must be a tissuefit.SpectralScene, got {type(scene).__name__}")
    checked = (("options", options, TraceOptions), ("spectral", spectral, SpectralOptions), ("records", records, RecordSpec))
    for name, value, kind in checked:
        if not isinstance(value, kind):
            raise TypeError(f"{name} must be a tissuefit.{kind.__name__}, got {type(value).__name__}")
    if options.path_stats:
        raise ValueError("options.path_stats: path statistics of spectral traces are not available yet; use trace() per band")
    if image is not None and not isinstance(image, ImageSpec):
        raise TypeError(f"image must be a tissuefit ImageSpec, got {type(image).__name__}")
    if isinstance(scene.source, EmissionSites) and image is None:
        raise ValueError("scene.source: emission sites are traced with an image (ImageSpec) only")
    tangents = tuple(tangents)
    if tangents and image is None:
        raise ValueError("tangents: the derivative directions belong to an image (give image=ImageSpec(...))")
    if isinstance(scene.source, CameraPaths) and image is None:
        raise ValueError("scene.source: paths from the camera are traced with an image (ImageSpec) only")
    if image is not None:
        image = dataclasses.replace(image, tangents=len(tangents), from_sites=isinstance(scene.source, EmissionSites))
        if isinstance(scene.source, CameraPaths):
            # paths from the camera score the source of their own grid (and the lights); no lobe
            image = dataclasses.replace(image, grid=scene.source.grid, from_camera=True, lobe=False)
            if scene.source.camera != image.camera:
                raise ValueError("scene.source: the camera paths belong to another camera than image.camera")
        if image.from_camera and tangents and scene.source.grid is not None and scene.source.tangents is None:
            raise ValueError("tangents: the camera paths' fluence carries no tangents; trace the lights with the same tangents")
        if image.from_sites and tangents and scene.source.tangent is None:
            raise ValueError("tangents: the emission sites carry no tangents; trace them with the same tangents")
    config = resolve_config(scene, options, spectral, records, image)
    dtype = jnp.dtype(options.precision)
    ndev = len(tuple(jax.devices() if devices is None else devices)[:photons])
    acc, exhausted = run_lanes(
        SpectralKernel(config), _Inputs(scene, tangents), key=key, photons=photons, chunks=chunks, progress=progress,
        devices=devices, resume=resume, on_chunk=on_chunk,
        new_lanes=lambda n: idle_lanes(n, config, dtype),
        new_acc=lambda: zeros_acc(config, ndev, dtype),
    )
    return _normalise(acc, photons, scene, config, exhausted)


def _valid_rows(a, counts: list[int]) -> np.ndarray | None:
    """The first counts[d] rows of each device's buffer a [devices, capacity, ...], concatenated (None
    for None). On the host: indexing the device arrays eagerly compiled a gather for every new count."""
    if a is None:
        return None
    a = np.asarray(a)
    return np.concatenate([a[d, :c] for d, c in enumerate(counts)])


@functools.partial(jax.jit, static_argnames=("config", "photons"))
def _packed(buf, scene: SpectralScene, config: SpectralConfig, photons: int) -> dict:
    """A record buffer [devices, capacity, ...] as PhotonRecords' fields: each device's valid rows
    packed first (devices in order; rows past the total count are padding), per-band powers per
    launched photon, floats in float64. One program per buffer shape (a program per record count, as
    eager indexing compiled, cost 1.2 s a trace); on the host the same took 0.125 s a buffer of 300 000
    rows, here 0.097 s (experiments/render/RESULTS.md)."""
    ndev, cap = buf.w.shape[:2]
    row = jnp.arange(cap)
    start = jnp.cumsum(buf.count) - buf.count
    target = jnp.where(row[None, :] < buf.count[:, None], start[:, None] + row[None, :], ndev * cap)
    source = jnp.zeros(ndev * cap, jnp.int64).at[target.reshape(-1)].set(jnp.arange(ndev * cap, dtype=jnp.int64), mode="drop")
    take = lambda a: None if a is None else jnp.take(jnp.reshape(a, (ndev * cap, *a.shape[2:])), source, axis=0)  # noqa: E731
    as64 = lambda a: None if a is None else (a.astype(jnp.float64) if jnp.issubdtype(a.dtype, jnp.floating) else a)  # noqa: E731
    rows = {k: take(getattr(buf, k)) for k in buf._fields if k not in ("count", "overflow")}
    act = jnp.asarray(config.active)
    power = jnp.zeros((ndev * cap, config.num_bands))
    band = rows["band"].astype(jnp.int64)
    if config.shared:
        w = band_weights(*(as64(rows[k]) for k in ("w", "spectrum", "path", "hits")), rows["band"],
                         medium_arrays(scene, config, jnp.float64))
        power = power.at[:, act].set(w / photons)
        band = act[band]
    else:
        power = power.at[jnp.arange(ndev * cap), band].set(as64(rows["w"]) / photons)
    out = {k: as64(rows[k]) for k in ("position", "direction", "path", "hits", "converted", "photon", "emission", *REPLAY_FIELDS)}
    if out["exc0"] is not None:  # shared paths: from the active slots to the band grid
        out["exc0"] = jnp.zeros((ndev * cap, config.num_bands)).at[:, act].set(out["exc0"])
    return dict(out, power=power, band=band)


def _records(buf, scene: SpectralScene, config: SpectralConfig, photons: int) -> PhotonRecords | None:
    """Concatenate the devices' buffers (valid rows only) and evaluate each record's per-band power."""
    if buf is None:
        return None
    count = int(np.sum(buf.count))
    rows = {k: None if v is None else np.asarray(v)[:count] for k, v in _packed(buf, scene, config, photons).items()}
    return PhotonRecords(count=count, overflow=int(np.sum(buf.overflow)), **rows)


def _normalise(acc, photons: int, scene: SpectralScene, config: SpectralConfig, exhausted: bool) -> SpectralResult:
    n = float(photons)
    total = lambda a: np.asarray(a).sum(0)  # noqa: E731
    totals, escape, deposit, flux = (total(a) for a in (acc.totals, acc.escape, acc.deposit, acc.flux))

    def mean_err(s, s2):
        m = s / n
        return m, np.sqrt(np.maximum(s2 / n - m * m, 0.0) / max(n - 1.0, 1.0))

    tot_mean, tot_err = mean_err(totals[:, 0], totals[:, 1])
    esc_mean, esc_err = mean_err(escape[..., 0], escape[..., 1])  # [bands, 4]
    rsp_total = float(total(acc.rsp)) / n
    power = np.asarray(scene.band_power(), dtype=np.float64)
    launched, emitted, converted, reconverted = (flux[:, k] / n for k in range(4))
    rd, tt, rd_fluor, tt_fluor = (esc_mean[:, k] for k in range(4))
    if config.shared:
        # Shared paths evaluate band weights only where light leaves or converts: heat per band is
        # what the balance leaves (an unbiased estimate; roulette is zero-mean and not resolved).
        a = launched + emitted - rd - tt - converted - reconverted
        a_fluor = emitted - rd_fluor - tt_fluor - reconverted
        roulette = roulette_fluor = np.zeros_like(a)
    else:
        a, a_fluor = (deposit[:, 0] + deposit[:, 1]) / n, deposit[:, 1] / n
        roulette, roulette_fluor = (deposit[:, 2] + deposit[:, 3]) / n, deposit[:, 3] / n
    return SpectralResult(
        photons=photons, bands=scene.tissue.bands, mode=config.mode, active=config.active,
        launched=launched, rsp=rsp_total * power, rd=rd, tt=tt, rd_fluor=rd_fluor, tt_fluor=tt_fluor,
        rd_stderr=esc_err[:, 0], tt_stderr=esc_err[:, 1], rd_fluor_stderr=esc_err[:, 2], tt_fluor_stderr=esc_err[:, 3],
        a=a, a_fluor=a_fluor, emitted=emitted, converted=converted, reconverted=reconverted,
        roulette=roulette, roulette_fluor=roulette_fluor,
        rsp_total=rsp_total, rd_total=tot_mean[0], tt_total=tot_mean[1], a_total=float(a.sum()),
        rd_total_stderr=tot_err[0], tt_total_stderr=tot_err[1],
        steps=total(acc.steps), outcome=Outcome.BUDGET_EXHAUSTED if exhausted else Outcome.SUCCESSFUL,
        surface_records=_records(acc.surface, scene, config, photons),
        volume_records=_records(acc.volume, scene, config, photons),
        **_image_parts(acc, config, photons, scene),
    )


def _image_parts(acc, config: SpectralConfig, photons: int, scene: SpectralScene) -> dict:
    """The image [batches, bands, H, W] per launched photon and the emission sites, from every device."""
    if config.image is None:
        return {}
    cam = config.image.camera
    k = config.tangents
    sums = np.asarray(acc.image).sum(0)[:-1].reshape(cam.batches, cam.height, cam.width, 1 + k, config.slots)
    # batches are photon index mod B: each batch is 1/B of the photons, so its own mean is B sum / N
    sums = np.moveaxis(sums, (3, 4), (1, 2)) * cam.batches / photons  # [B, 1 + K, slots, H, W]
    full = np.zeros((cam.batches, 1 + k, config.num_bands, cam.height, cam.width))
    full[:, :, np.asarray(config.active)] = sums
    out = {"image": full[:, 0], "image_tangents": full[:, 1:] if k else None}
    if acc.fluence is not None:
        fluence = fluence_of(acc.fluence, config.image.grid, photons)
        out["fluence"], out["fluence_tangents"] = fluence[0], fluence[1:] if k else None
    if acc.sites is not None:
        sites = acc.sites
        take = functools.partial(_valid_rows, counts=[int(c) for c in np.asarray(sites.count)])

        out["sites"] = EmissionSites(position=take(sites.position).astype(np.float64), layer=take(sites.layer),
                                     medium=take(sites.medium), power=take(sites.power).astype(np.float64),
                                     origin=take(sites.origin),
                                     tangent=None if sites.tangent is None else take(sites.tangent).astype(np.float64))
        out["sites_overflow"] = int(np.sum(sites.overflow))
    return out
