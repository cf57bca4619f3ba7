"""`render(tissue, endoscope, ...)`: what the endoscope's camera sees, as a stack [bands, H, W].

Four stages, each a function below:

1. trace: the lights' launches (only those that can reach the camera's view) into the tissue.
   With the next-event estimator ("nee", default) the trace itself scores the camera image
   (`tissuefit.transport.trace_image`); with the photon-map estimator ("photon-map", the paper's) it
   keeps photon records.
2. maps (photon-map only): surface and volume photon maps of the records, bandwidths chosen from
   them (`_bandwidth.py`).
3. geometry: the camera's rays and where they meet the tissue (`_geometry.py`); for the photon
   map also each pixel's march points and Fresnel factors.
4. estimate: the diffuse radiance (next-event image, smoothed with the error-optimal bandwidth
   of `_denoise.py`; or the photon-map shading of `_shading.py`), plus the lights' specular
   reflection, times the observation filter.

Units: radiance per unit power of the illumination [1/(cm^2 sr)] per band (band powers from the
spectrum sum to 1; the head's two lights emit 1 together). Pixels whose ray misses the tissue are 0.
"""

from __future__ import annotations

import dataclasses
import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import bucket, check_positive_int
from .._setup import float64
from ..photonmap import build_surface_map, build_volume_map
from ..scene import AbstractSpectrum, FlatSpectrum, SpectralScene, SpectralTissue
from ..transport import RecordSpec, SpectralOptions, TraceOptions, trace_image, trace_spectral
from ._bandwidth import auto_radius, band_share
from ._denoise import smooth, sure_smooth
from ._endoscope import Endoscope
from ._geometry import View, camera_view, march_points_of, march_shading
from ._illumination import ConeLights, Floodlight
from ._options import RenderOptions
from ._shading import Shading, image_of, shade, specular_term


class MapTerms(eqx.Module):
    """What the photon-map estimator made (numpy unless noted).

    - `surface`, `fluorescence` [bands, H, W]: the surface term and the march's fluorescence (in
      "surface" fluorescence mode the fluorescence is inside `surface`).
    - `truncation` [bands]: exp(-mut S dx) of the top layer, the part of a uniform source deeper
      than the march that is left out.
    - `surface_radius`, `volume_radius` (arrival map), `emission_radius` (emission map),
      `step_length` [cm]; `surface_photons`, `volume_photons`, `emission_photons`: records in
      the maps (0 where not built).
    - `records`: the (surface, arrival, emission) `PhotonRecords` the maps hold, powers per unit
      illumination power (None where not built); `maps` (surface, arrival, emission maps) and
      `shading` (`Shading`): what `tissuefit.replay.RenderReplay` replays.
    """

    surface: np.ndarray
    fluorescence: np.ndarray
    truncation: np.ndarray
    surface_radius: float
    volume_radius: float | None
    emission_radius: float | None
    step_length: float
    surface_photons: int
    volume_photons: int
    emission_photons: int
    records: tuple | None = None
    maps: tuple | None = None
    shading: Shading | None = None


class RenderResult(eqx.Module):
    """A rendered stack and how it was made (numpy arrays).

    - `stack` [bands, H, W]: radiance per unit illumination power [1/(cm^2 sr)] = `diffuse` +
      `specular` (each [bands, H, W]), times the observation filter.
    - `diffuse`: the light leaving the tissue; `specular`: the lights' reflection at the surface.
    - `estimator`: "nee" or "photon-map" (`RenderOptions.estimator`).
    - next-event estimator: `raw` [bands, H, W] the unsmoothed diffuse image and `variance` its
      Monte Carlo variance (from the photons' independent batches); `smoothing_px` [bands] the
      Gaussian width the diffuse image was smoothed with [pixels] (0: none).
    - photon-map estimator: `maps` (`MapTerms`).
    - `wavelengths` [bands] nm; `hit` [H, W]: the pixel's ray meets the tissue; `covered` [H, W]:
      some light reached the pixel (next-event: a nonzero raw pixel; photon map: the surface
      kernel found a record).
    - `photons`: launches traced, `launched_fraction`: the illumination's power they carry.
    - `filter_transmission` [bands]: the observation filter's band averages (ones without one).
    - `timings` (dict of seconds per stage: trace, maps, geometry, estimate; the next-event trace's
      parts as trace_launches, trace_sites, trace_paths); `seconds` their total.
    - `trace`: the `SpectralResult` of the launches (tallies; records dropped); `outcome` its `Outcome`.
    - next-event estimator with `keep_batches`: `batches` [batches, bands, H, W], the raw diffuse
      image of each independent batch of photons; with `tangents`: `tangents` [K, bands, H, W] the
      raw diffuse image's derivative along each tangent tissue (path replay), and per batch
      `tangent_batches` [batches, K, bands, H, W] with `keep_batches`. All times the filter.
    """

    stack: np.ndarray
    diffuse: np.ndarray
    specular: np.ndarray
    estimator: str
    wavelengths: np.ndarray
    hit: np.ndarray
    covered: np.ndarray
    photons: int
    launched_fraction: float
    filter_transmission: np.ndarray
    timings: dict
    trace: object
    raw: np.ndarray | None = None
    variance: np.ndarray | None = None
    smoothing_px: np.ndarray | None = None
    maps: MapTerms | None = None
    batches: np.ndarray | None = None
    tangents: np.ndarray | None = None
    tangent_batches: np.ndarray | None = None

    @property
    def outcome(self):
        """How the render's trace ended (`tissuefit.Outcome`, that of `trace`): BUDGET_EXHAUSTED
        when `TraceOptions.max_steps` stopped it early (the image then misses light)."""
        return self.trace.outcome

    @property
    def seconds(self) -> float:
        """The render's time [s]: the sum of its stages (`timings` without the trace's parts)."""
        return float(sum(v for k, v in self.timings.items() if not k.startswith("trace_")))


class _Setup(eqx.Module):
    """The render's inputs, checked and resolved (defaults filled in)."""

    tissue: SpectralTissue
    endoscope: Endoscope
    spectrum: AbstractSpectrum
    illumination: object
    options: RenderOptions
    trace_options: TraceOptions
    spectral: SpectralOptions
    transmission: np.ndarray


def _setup(tissue, endoscope, spectrum, illumination, options, trace_options, spectral, observation_filter) -> _Setup:
    if not isinstance(tissue, SpectralTissue):
        raise TypeError(f"tissue is a {type(tissue).__name__}, not a SpectralTissue")
    endoscope = Endoscope() if endoscope is None else endoscope
    if not isinstance(endoscope, Endoscope):
        raise TypeError(f"endoscope is a {type(endoscope).__name__}, not an Endoscope")
    if not isinstance(options, RenderOptions):
        raise TypeError(f"options is a {type(options).__name__}, not a RenderOptions")
    spectrum = FlatSpectrum() if spectrum is None else spectrum
    illumination = ConeLights(endoscope) if illumination is None else illumination
    if not isinstance(illumination, (ConeLights, Floodlight)):
        raise TypeError(f"illumination is a {type(illumination).__name__}; allowed ConeLights or Floodlight")
    march = tissue.fluorescent and options.estimator == "photon-map" and options.fluorescence == "march"
    if spectral is None:
        # The march needs converted photons; with analog conversions the paper's 300 000 launches
        # leave ~1e3 emission records in view. Odds x10 (unbiased): the angle study's CNR 0.20 ->
        # 0.67 at 0 deg (experiments/render). Next-event images sample no conversion at all.
        spectral = SpectralOptions(conversion_boost=10.0 if march else 1.0)
    transmission = np.ones(tissue.bands.num_bands)
    if observation_filter is not None:
        if not isinstance(observation_filter, AbstractSpectrum):
            raise TypeError(f"observation_filter is a {type(observation_filter).__name__}, not a spectrum")
        transmission = np.asarray(tissue.bands.average(observation_filter), np.float64)
        if not (np.all(np.isfinite(transmission)) and np.all(transmission >= 0) and np.all(transmission <= 1 + 1e-12)):
            raise ValueError(f"observation_filter: band transmissions {transmission.round(4).tolist()}; allowed values in [0, 1]")
    return _Setup(tissue=tissue, endoscope=endoscope, spectrum=spectrum, illumination=illumination, options=options,
                  trace_options=trace_options, spectral=spectral, transmission=transmission)


@float64
def render(
    tissue: SpectralTissue,
    endoscope: Endoscope | None = None,
    *,
    spectrum: AbstractSpectrum | None = None,
    photons: int = 300_000,
    key=None,
    illumination=None,
    options: RenderOptions = RenderOptions(),
    trace_options: TraceOptions = TraceOptions(),
    spectral: SpectralOptions | None = None,
    chunks: int = 1,
    progress=None,
    keep_records: bool = False,
    path_statistics: bool = False,
    observation_filter: AbstractSpectrum | None = None,
    tangents: tuple = (),
    keep_batches: bool = False,
) -> RenderResult:
    """Trace the illumination into `tissue` and render the camera's stack (module docstring).

    - `tissue`: a `SpectralTissue` (its band grid is the stack's); `endoscope`: camera and lights
      geometry (default `Endoscope()`); `spectrum`: the lights' spectrum (default flat white).
    - `photons`: launches sampled from the lights (those that cannot reach the camera's view are
      not traced; see `RenderResult.launched_fraction`); `key`: PRNG key (default key(0)).
    - `illumination`: default the endoscope's cone lights; `Floodlight(radius)` for a wide beam.
    - `options`: `RenderOptions` (estimator and its settings); `trace_options`, `spectral`,
      `chunks`, `progress` (a callable `progress(photons_done)`): passed to the tracer
      (`spectral` default: automatic mode; conversion_boost 10 for the photon map's march). With
      fluorescence from the camera the lights' photons play roulette from 0.003 of their launch
      weight and the camera's paths from their own threshold, each unless `trace_options`' is higher
      (`tissuefit.transport._image`: `LIGHT_ROULETTE`, `PATH_ROULETTE`).
    - photon-map estimator only: `keep_records` keeps the records, maps and shading in
      `RenderResult.maps`; `path_statistics` makes the records carry what path replay needs
      (`tissuefit.replay.RenderReplay`).
    - `observation_filter`: the camera's filter transmission (e.g. `LongpassFilter`, or a
      `TabulatedSpectrum` of values in [0, 1]); every term is multiplied by its band average.
    - next-event estimator only: `tangents`, tissues shaped like `tissue` whose leaves are
      directions in its coefficients (`jax.jvp` of a parametrised tissue): the raw image's
      derivative along each, by path replay (`RenderResult.tangents`); `keep_batches` keeps the
      batch images (and their tangents) the image and its variance come from.
    Returns a `RenderResult`.
    """
    setup = _setup(tissue, endoscope, spectrum, illumination, options, trace_options, spectral, observation_filter)
    photons = check_positive_int("photons", photons, high=2**40)
    key = jax.random.key(0) if key is None else key
    camera_side = setup.options.estimator != "photon-map"
    if camera_side and (keep_records or path_statistics):
        raise ValueError("render: keep_records and path_statistics belong to the photon-map estimator "
                         "(options.estimator = 'photon-map'); next-event images keep no records")
    tangents = tuple(tangents)
    if not camera_side and (tangents or keep_batches):
        raise ValueError("render: tangents and keep_batches belong to the 'nee' and 'adjoint' estimators; "
                         "photon-map renders are differentiated by tissuefit.replay.render_replay")
    if setup.options.estimator == "adjoint" and not isinstance(setup.illumination, ConeLights):
        raise ValueError("render: estimator 'adjoint' connects paths to the endoscope's cone lights; a "
                         f"{type(setup.illumination).__name__} cannot be hit by a path (use estimator 'nee')")
    timings = {}
    t = time.perf_counter()
    view = camera_view(setup.endoscope, setup.options.margin)
    timings["geometry"] = time.perf_counter() - t
    t = time.perf_counter()
    source, kept, fraction = setup.illumination.launches(photons, jax.random.fold_in(key, 1), setup.options.halton,
                                                         view.footprint)
    scene = SpectralScene(setup.tissue, source=source, spectrum=setup.spectrum)
    if camera_side:
        adjoint = setup.options.estimator == "adjoint"
        lights = setup.endoscope.area_lights() if adjoint else None
        image = trace_image(scene, setup.endoscope.camera(setup.options.batches), key=key, photons=kept,
                            options=setup.trace_options, spectral=setup.spectral, splits=setup.options.splits,
                            site_rate=setup.options.site_rate, lobe=setup.options.lobe, progress=progress, tangents=tangents,
                            fluorescence="adjoint" if adjoint else setup.options.nee_fluorescence,
                            paths=setup.options.paths, lights=lights, launched_power=fraction)
        timings["trace"] = time.perf_counter() - t
        return _finish_nee(setup, view, image, kept, fraction, timings, keep_batches)
    traced = _trace_records(setup, scene, key, kept, chunks, progress, path_statistics)
    timings["trace"] = time.perf_counter() - t
    return _finish_maps(setup, view, traced, kept, fraction, timings, keep_records or path_statistics, path_statistics)


# ---------------------------------------------------------------------------------------------
# next-event estimator


def _finish_nee(setup: _Setup, view: View, image, kept: int, fraction: float, timings: dict, keep_batches: bool) -> RenderResult:
    """Stage 4 for the next-event image: smoothing, specular term, filter."""
    t = time.perf_counter()
    timings.update({f"trace_{stage}": seconds for stage, seconds in image.timings.items()})
    e = setup.endoscope
    hit = np.asarray(view.hit).reshape(e.height, e.width)
    raw = image.image * fraction
    variance = image.variance * fraction**2
    options = setup.options
    if options.smoothing_px is not None:
        diffuse, _ = smooth(raw, options.smoothing_px, hit)
        sigma = np.full(raw.shape[0], float(options.smoothing_px))
    elif options.smoothing == "sure":
        diffuse, sigma, _ = sure_smooth(raw, variance, hit)
    else:
        diffuse, sigma = np.where(hit, raw, 0.0), np.zeros(raw.shape[0])
    specular = _specular(setup, view)
    timings["estimate"] = time.perf_counter() - t
    w = setup.transmission[:, None, None]
    covered = hit & (raw.sum(0) > 0)
    return RenderResult(
        stack=(diffuse + specular) * w, diffuse=diffuse * w, specular=specular * w, estimator=setup.options.estimator,
        wavelengths=setup.tissue.bands.wavelengths, hit=hit, covered=covered, photons=kept, launched_fraction=fraction,
        filter_transmission=setup.transmission, timings=timings, trace=image.trace, raw=raw * w,
        variance=variance * w**2, smoothing_px=sigma,
        batches=image.batches * fraction * w if keep_batches else None,
        tangents=None if image.tangent_batches is None else image.tangents * fraction * w,
        tangent_batches=image.tangent_batches * fraction * w if keep_batches and image.tangent_batches is not None else None,
    )


def _specular(setup: _Setup, view: View) -> np.ndarray:
    """The lights' specular reflection [bands, H, W] (`specular_term`), zeros when switched off."""
    e, nb = setup.endoscope, setup.tissue.bands.num_bands
    if setup.options.specular_deg <= 0:
        return np.zeros((nb, e.height, e.width))
    geo = setup.tissue.geometry
    cos_o = jnp.where(view.hit, view.direction[:, 2], 1.0)
    irradiance, incidence = setup.illumination.irradiance(view.points)
    band_power = jnp.asarray(setup.spectrum.band_power(setup.tissue.bands), jnp.float64)
    lobe = specular_term(view.points, -view.direction, cos_o, irradiance, incidence, float(geo.n_above),
                         float(np.asarray(geo.n)[0]), math.radians(setup.options.specular_deg), band_power)
    return np.asarray(image_of(view.hit.reshape(e.height, e.width), lobe))


# ---------------------------------------------------------------------------------------------
# photon-map estimator


def _trace_records(setup: _Setup, scene, key, kept: int, chunks: int, progress, path_statistics: bool):
    """Stage 1 for the photon map: trace with surface (and for the march, volume and emission)
    records, the volume buffer grown until nothing overflows."""
    march = setup.tissue.fluorescent and setup.options.fluorescence == "march"
    capacity = bucket(setup.options.volume_capacity * kept) if march else 0
    for _ in range(4):
        # capacities rounded up to buckets, so that renders of similar photon counts share a compile
        records = RecordSpec(surface=bucket(kept), volume=capacity, emission=march, replay=path_statistics)
        traced = trace_spectral(scene, key=key, photons=kept, options=setup.trace_options, spectral=setup.spectral,
                                records=records, chunks=chunks, progress=progress)
        vol = traced.volume_records
        if vol is None or vol.overflow == 0:
            return traced
        capacity = bucket((vol.count + vol.overflow) * 1.25)  # retry with room
    raise RuntimeError("render: the volume record buffer kept overflowing")  # pragma: no cover


def _maps(setup: _Setup, view: View, traced, fraction: float, step_length: float, padded: bool):
    """Stage 2: the surface map (with a count column) and the arrival and emission volume maps, and
    their bandwidths (fixed, or chosen from the records). Returns (records, maps, radii)."""
    options = setup.options
    march = setup.tissue.fluorescent and options.fluorescence == "march"

    def per_illumination(r):
        return eqx.tree_at(lambda x: x.power, r, r.power * fraction)

    surf = traced.surface_records
    if march:
        surf = surf.select(~surf.converted)
    surf = per_illumination(surf)
    hits = np.asarray(view.points)[np.asarray(view.hit)]
    r_s = options.surface_radius or auto_radius(surf.position[:, :2], hits[:, :2], options.neighbours, 1,
                                                band_share(surf.power))
    if padded:
        # buffers and maps rounded up to a few sizes: a fit's re-traces (record counts and extents that
        # differ a little) then reuse the replay's and the maps' compiles
        surf = surf.padded(bucket(surf.count))
    # one extra column of ones counts the records under the kernel (coverage)
    counting = eqx.tree_at(lambda r: r.power, surf, np.concatenate([surf.power, np.ones((surf.capacity, 1))], axis=1))
    smap = build_surface_map(counting, cell=r_s, round_up=padded)
    arrivals = emissions = vmap_arr = vmap_em = r_v = r_e = None
    if march:
        vol = traced.volume_records
        arrivals, emissions = per_illumination(vol.select(~vol.emission)), per_illumination(vol.select(vol.emission))
        pts = march_points_of(view, setup.tissue, options, step_length)
        r_v = options.volume_radius or auto_radius(arrivals.position, pts, options.neighbours, 2, band_share(arrivals.power))
        # emission records are ~10-20x sparser than arrivals: their own bandwidth, from their density
        r_e = options.volume_radius or (auto_radius(emissions.position, pts, options.neighbours, 3, band_share(emissions.power))
                                        if emissions.count else r_v)
        if padded:
            arrivals, emissions = (r.padded(bucket(r.count)) for r in (arrivals, emissions))
        if arrivals.count:
            vmap_arr = build_volume_map(arrivals, cell=r_v, round_up=padded)
        if emissions.count:
            vmap_em = build_volume_map(emissions, cell=r_e, round_up=padded)
    radii = (float(r_s), None if r_v is None else float(r_v), None if r_e is None else float(r_e))
    return (surf, arrivals, emissions), (smap, vmap_arr, vmap_em), radii


def _step_length(setup: _Setup, active) -> float:
    """The march's step length [cm]: the option, else one mean free path of the top layer's densest lit band."""
    if setup.options.step_length:
        return float(setup.options.step_length)
    mua, mus, _ = (np.asarray(a, np.float64) for a in setup.tissue.properties())
    mut_top = (mua + mus)[0, list(active)]
    positive = mut_top[mut_top > 0]
    return 1.0 / float(positive.min()) if positive.size else 0.01


def _finish_maps(setup: _Setup, view: View, traced, kept: int, fraction: float, timings: dict, keep: bool,
                 padded: bool) -> RenderResult:
    """Stages 2-4 for the photon map: maps, shading geometry, estimates, specular term, filter."""
    e = setup.endoscope
    t = time.perf_counter()
    dx = _step_length(setup, traced.active)
    records, maps, radii = _maps(setup, view, traced, fraction, dx, padded)
    timings["maps"] = time.perf_counter() - t
    t = time.perf_counter()
    mua, mus, g = (jnp.asarray(a, jnp.float64) for a in setup.tissue.properties())
    shading = march_shading(view, e, setup.tissue, setup.options, step_length=dx, radii=radii,
                            volume_maps=maps[1:], traced_g=g, active=traced.active)
    timings["geometry"] += time.perf_counter() - t
    t = time.perf_counter()
    l_surface, l_fluor, count = shade(shading, mua, mus, g, *maps)
    hit = view.hit.reshape(e.height, e.width)
    surface, fluor = (np.asarray(image_of(hit, a)) for a in (l_surface, l_fluor))
    specular = _specular(setup, view)
    timings["estimate"] = time.perf_counter() - t
    w = setup.transmission[:, None, None]
    smap, vmap_arr, vmap_em = maps
    terms = MapTerms(
        surface=surface * w, fluorescence=fluor * w,
        truncation=np.exp(-np.asarray(mua + mus)[0] * setup.options.steps * dx), surface_radius=radii[0],
        volume_radius=radii[1], emission_radius=radii[2], step_length=float(dx), surface_photons=int(records[0].count),
        volume_photons=0 if vmap_arr is None else int(vmap_arr.count),
        emission_photons=0 if vmap_em is None else int(vmap_em.count),
        records=records if keep else None, maps=maps if keep else None, shading=shading if keep else None,
    )
    hit = np.asarray(hit)
    return RenderResult(
        stack=(surface + fluor + specular) * w, diffuse=(surface + fluor) * w, specular=specular * w,
        estimator="photon-map", wavelengths=setup.tissue.bands.wavelengths, hit=hit,
        covered=(np.asarray(count) > 0).reshape(hit.shape) & hit, photons=kept, launched_fraction=fraction,
        filter_transmission=setup.transmission, timings=timings,
        trace=dataclasses.replace(traced, surface_records=None, volume_records=None), maps=terms,
    )
