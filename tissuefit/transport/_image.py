"""`trace_image`: a camera image by next-event estimation, fluorescence by emission sites.

Photons are launched from the scene's source in chunks. Each chunk is traced once with the camera
(`_nee.py`): every interaction scores the light it scatters and the fluorescence it emits straight
to the camera, and fluorescent scenes sample emission sites. The sites are then traced as photons
of their own (each `splits` times, the power divided), scoring the fluorescence that scatters
before it escapes, and sampling sites of their own where fluorescence light is converted again
(next generation), up to `generations`. Chunks bound the memory the sites take.

The image is the sum of all of it per launched photon; the photons (and all light descending
from each) are split into `camera.batches` independent batch images, whose spread is its Monte
Carlo noise.

With `fluorescence="adjoint"` fluorescence is traced from the camera instead (`_adjoint.py`): the
launches tally the excitation fluence into a grid and score only the scattered light; then
`paths` paths per pixel start from the camera and score the fluorescence source the grid holds.
Batch b of those paths uses batch b's grid, so the batches stay independent.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import bucket, check_positive_int, check_range
from .._setup import float64
from ..scene import SpectralScene
from ._adjoint import POWER_FLOOR, CameraPaths, FluenceGrid, camera_footprint, smooth_fluence, smooth_like
from ._camera import PinholeCamera
from ._config import TraceOptions
from ._lights import AreaLights
from ._nee import EmissionSites, ImageSpec
from ._spectral import SpectralOptions, SpectralResult, trace_spectral

CHUNK_PHOTONS = 1 << 20
"""Launches per chunk of `trace_image` (its emission sites are traced before the next chunk)."""

SITES_PER_PHOTON = 1.0
"""First guess of the emission sites a launch leaves, for the site buffer (grown when it overflows)."""


class ImageResult(eqx.Module):
    """A next-event image and how it was made (numpy).

    - `batches` [batches, bands, H, W]: radiance per unit launched power [1/(cm^2 sr)] of each
      independent batch of photons; `image` [bands, H, W] their mean; `variance` [bands, H, W] the
      Monte Carlo variance of `image` (the batches' spread / batches).
    - `tangent_batches` [batches, K, bands, H, W]: with `tangents`, each batch's derivative along
      each tangent direction (path replay of every scored contribution); `tangents` their mean.
    - `photons`: launches traced; `sites` [generations]: emission sites traced in each generation;
      `emitted` [generations]: their power per launched photon (summed over bands);
      `untraced`: the power of sites of the generation after the last, left out (per launched photon).
    - `trace`: the `SpectralResult` of the launches (tallies of the first chunk, records dropped).
    - `timings`: seconds per stage ("launches", "sites", "paths").
    - estimates from the camera: `camera_batches` [batches, bands, H, W] the part of `batches` the
      camera's paths scored (`fluorescence_batches` the same when they scored fluorescence only),
      `grid` the `FluenceGrid`, `grid_smoothing` [excitation bands] the lateral width [cells] its
      fluence was smoothed with (`smooth_fluence`), `paths` the paths traced per pixel.
    """

    batches: np.ndarray
    photons: int
    sites: tuple
    emitted: tuple
    untraced: float
    trace: SpectralResult
    timings: dict
    tangent_batches: np.ndarray | None = None
    fluorescence_batches: np.ndarray | None = None
    camera_batches: np.ndarray | None = None
    grid: FluenceGrid | None = None
    paths: int = 0
    grid_smoothing: np.ndarray | None = None

    @property
    def image(self) -> np.ndarray:
        return self.batches.mean(axis=0)

    @property
    def tangents(self) -> np.ndarray | None:
        return None if self.tangent_batches is None else self.tangent_batches.mean(axis=0)

    @property
    def variance(self) -> np.ndarray:
        b = self.batches.shape[0]
        return self.batches.var(axis=0, ddof=1) / b if b > 1 else np.full(self.batches.shape[1:], np.nan)


def _with_sites(scene: SpectralScene, sites: EmissionSites) -> SpectralScene:
    return SpectralScene(scene.tissue, source=sites, spectrum=scene.spectrum)


def _traced_with_room(scene, key, photons, options, spectral, camera, site_rate, lobe, capacity, chunks, progress, tangents):
    """trace_spectral with a site buffer grown (and the trace repeated) until nothing overflows."""
    for _ in range(6):
        spec = ImageSpec(camera=camera, sites=capacity if scene.tissue.fluorescent else 0, site_rate=site_rate, lobe=lobe)
        out = trace_spectral(scene, key=key, photons=photons, options=options, spectral=spectral, image=spec,
                             chunks=chunks, progress=progress, tangents=tangents)
        if not out.sites_overflow:
            return out, capacity
        capacity = bucket((out.sites.count + out.sites_overflow) * 1.25)
    raise RuntimeError("trace_image: the emission-site buffer kept overflowing")  # pragma: no cover


def _add(total, part, scale):
    """total + part * scale, with None for nothing yet (or no part)."""
    if part is None:
        return total
    return part * scale if total is None else total + part * scale


@float64
def trace_image(
    scene: SpectralScene,
    camera: PinholeCamera,
    *,
    key,
    photons: int,
    options: TraceOptions = TraceOptions(),
    spectral: SpectralOptions = SpectralOptions(),
    splits: int = 1,
    site_rate: float = 0.1,
    lobe: bool = True,
    generations: int = 3,
    chunk_photons: int = CHUNK_PHOTONS,
    progress=None,
    tangents: tuple = (),
    fluorescence: Literal["sites", "adjoint"] = "sites",
    paths: int = 32,
    grid: FluenceGrid | None = None,
    path_options: TraceOptions | None = None,
    lights: AreaLights | None = None,
    launched_power: float = 1.0,
) -> ImageResult:
    """Trace `photons` launches of `scene` and score what `camera` sees (module docstring).

    - `scene`: a `SpectralScene` whose source launches from above the tissue (a `LaunchList` for
      an endoscope's lights); `camera`: a `PinholeCamera`.
    - `key` (keyword-only), `photons`, `options`, `spectral`: as for `trace_spectral`
      (`spectral.conversion_boost` plays no part: no conversion is sampled).
    - `splits`: photons traced per emission site (splitting at conversion; their power divided).
    - `site_rate`: emission sites per interaction of a launch-weight photon where a band's strongest
      emitter is (`_nee.py`): more sites, each with less power.
    - `lobe`: also score the camera lobe (`_nee.py`): a vertex sampled around the direction to the
      camera at every scattering, combined with the photon's own next vertex by multiple importance
      sampling; it cuts the variance that a forward-peaked phase function gives the connections.
    - `generations`: fluorescence generations traced (light converted again by another
      fluorophore is the second); what the last leaves is reported in `ImageResult.untraced`.
    - `chunk_photons`: launches per chunk (bounds the emission sites held at once).
    - `progress`: optional callable `progress(launches_done)`.
    - `tangents`: tissues shaped like `scene.tissue` whose leaves are directions in its coefficients:
      the image's derivative along each is scored too (`ImageResult.tangent_batches`).
    - `fluorescence`: "sites" (emission sites from the lights' side) or "adjoint" (from the camera,
      `_adjoint.py`): `paths` per pixel, through `grid` (default
      `FluenceGrid.covering` the camera's footprint), traced with `path_options` (default `options`
      with the paths' own roulette threshold, `PATH_ROULETTE`); the lights' photons then play roulette
      from `LIGHT_ROULETTE` of their launch weight (or `options`' threshold, if higher).
    - `lights`: `AreaLights` (with fluorescence="adjoint"): the scattered light is traced from the
      camera too (`_lights.py`); the launches then only tally the fluence (none are traced without
      fluorescence). `launched_power`: the power of the lights' units that `scene`'s launches carry
      (the image is per unit launched power: the lights' light is divided by it).
    Returns an `ImageResult`.
    """
    if not isinstance(scene, SpectralScene):
        raise TypeError(f"scene must be a tissuefit.SpectralScene, got {type(scene).__name__}")
    if not isinstance(camera, PinholeCamera):
        raise TypeError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
    photons = check_positive_int("photons", photons, high=2**40)
    splits = check_positive_int("splits", splits, high=1024)
    generations = check_positive_int("generations", generations, high=16)
    chunk_photons = check_positive_int("chunk_photons", chunk_photons, high=2**31)
    check_range("site_rate", site_rate, unit="sites per interaction", low=0.0, high=1.0, low_open=True)
    if fluorescence not in ("sites", "adjoint"):
        raise ValueError(f"fluorescence = {fluorescence!r}; allowed 'sites' or 'adjoint'")
    if lights is not None and not isinstance(lights, AreaLights):
        raise TypeError(f"lights must be AreaLights, got {type(lights).__name__}")
    if lights is not None and fluorescence != "adjoint":
        raise ValueError("lights: the scattered light is traced from the camera with fluorescence='adjoint' only")
    if fluorescence == "adjoint" and (scene.tissue.fluorescent or lights is not None):
        return _trace_adjoint(scene, camera, key=key, photons=photons, options=options, spectral=spectral, lobe=lobe,
                              chunk_photons=chunk_photons, progress=progress, tangents=tuple(tangents), paths=paths,
                              grid=grid, path_options=path_options, lights=lights, launched_power=launched_power)
    timings = {"launches": 0.0, "sites": 0.0}
    sums = dsums = None  # batch sums (per batch: sum over its photons of their radiance) and their tangents
    tangents = tuple(tangents)
    emitted = np.zeros(generations)
    counts = np.zeros(generations, np.int64)
    untraced = 0.0
    first = None
    capacity = bucket(min(photons, chunk_photons) * SITES_PER_PHOTON)
    starts = list(range(0, photons, chunk_photons))
    for c, start in enumerate(starts):
        n = min(chunk_photons, photons - start)
        ck = jax.random.fold_in(key, c)
        t0 = time.perf_counter()
        done = (lambda k, s=start: progress(s + k)) if progress is not None else None
        out, capacity = _traced_with_room(scene, ck, n, options, spectral, camera, site_rate, lobe, capacity, 1, done,
                                          tangents)
        timings["launches"] += time.perf_counter() - t0
        first = first or out
        sums = _add(sums, out.image, n / camera.batches)
        dsums = _add(dsums, out.image_tangents, n / camera.batches)
        sites = out.sites
        t1 = time.perf_counter()
        for gen in range(generations):
            if sites is None or sites.count == 0:
                break
            counts[gen] += sites.count
            emitted[gen] += float(np.sum(sites.power))
            launched = sites.padded(bucket(sites.count), splits)
            m = sites.count * splits
            last = gen == generations - 1
            gk = jax.random.fold_in(ck, 1000 + gen)
            sub, _ = _traced_with_room(_with_sites(scene, launched), gk, m, options, spectral, camera, site_rate, lobe,
                                       bucket(m * SITES_PER_PHOTON), 1, None, tangents)
            sums = _add(sums, sub.image, m / camera.batches)
            dsums = _add(dsums, sub.image_tangents, m / camera.batches)
            sites = sub.sites
            if last and sites is not None:
                untraced += float(np.sum(sites.power))
        timings["sites"] += time.perf_counter() - t1
    batches = sums * camera.batches / photons
    return ImageResult(batches=batches, photons=photons, sites=tuple(int(c) for c in counts),
                       tangent_batches=None if dsums is None else dsums * camera.batches / photons,
                       emitted=tuple(float(e) / photons for e in emitted), untraced=untraced / photons,
                       trace=dataclasses.replace(first, sites=None, image=None), timings=timings)


def fluorescence_bands(scene: SpectralScene) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """(excitation bands, emission bands) of a fluorescent scene: the lit bands some medium converts
    from (above `POWER_FLOOR` of the strongest), and the bands it converts them into (concrete values)."""
    power = np.asarray(scene.band_power())
    conv = np.asarray(scene.tissue.conversion())  # [media, bands, bands]
    strength = power * conv.max((0, 2))
    excite = (power > 0) & (strength > 0) & (strength >= POWER_FLOOR * strength.max())
    emit = conv[:, excite].sum((0, 1)) > 0
    return tuple(int(b) for b in np.nonzero(excite)[0]), tuple(int(b) for b in np.nonzero(emit)[0])


PATH_ROULETTE = 0.06
"""Roulette threshold of the camera's paths, relative to their launch weight (1 / the bands they
carry, shared paths): a path whose score has fallen to ~6 % of its start plays roulette. Measured on
the lesion scene at 128 x 128 (experiments/render/RESULTS.md): relative to MCML's 1e-4 the paths
took 6.8 s instead of 12.0 s for the same error (5.4 % against 5.2 %); at 20 % the error grew more
than the time fell."""


def path_roulette(options: TraceOptions, bands: int) -> TraceOptions:
    """`options` with the camera paths' roulette threshold (`PATH_ROULETTE`) for paths carrying `bands` bands."""
    return dataclasses.replace(options, roulette_threshold=max(options.roulette_threshold, PATH_ROULETTE / max(bands, 1)))


LIGHT_ROULETTE = 0.003
"""Roulette threshold of the lights' photons when the fluorescence is traced from the camera (relative
to their launch weight). Each of their steps scores a next-event connection to the camera (and the
lobe, and the fluence), ~10x a plain step; below a few thousandths of its launch weight a photon's
connections carry almost nothing. Measured (experiments/render/RESULTS.md, unsmoothed, 3 renders
each): against MCML's 1e-4 the same noise in every band group in 0.88x the time on the paper's lesion
scene (128 x 128) and 0.76x on the PpIX droplet (64 x 64); at 0.01 the droplet's noise grew 6 %."""


def light_roulette(options: TraceOptions) -> TraceOptions:
    """`options` with the lights' roulette threshold (`LIGHT_ROULETTE`) of renders with fluorescence from the camera."""
    return dataclasses.replace(options, roulette_threshold=max(options.roulette_threshold, LIGHT_ROULETTE))


def lit_bands(scene: SpectralScene) -> tuple[int, ...]:
    """The bands the scene's source lights, above `POWER_FLOOR` of the strongest (concrete values)."""
    power = np.asarray(scene.band_power())
    return tuple(int(b) for b in np.nonzero((power > 0) & (power >= POWER_FLOOR * power.max()))[0])


def _trace_adjoint(scene, camera, *, key, photons, options, spectral, lobe, chunk_photons, progress, tangents, paths, grid,
                   path_options, lights, launched_power) -> ImageResult:
    """`trace_image` with estimates from the camera (module docstring)."""
    paths = check_positive_int("paths", paths, high=1 << 20)
    excite, emit = fluorescence_bands(scene) if scene.tissue.fluorescent else ((), ())
    lit = lit_bands(scene) if lights is not None else ()
    carried = tuple(sorted(set(emit) | set(lit)))
    if path_options is None:
        path_options = path_roulette(options, len(carried))
    if grid is None and excite:
        grid = FluenceGrid.covering(camera_footprint(camera), scene.tissue, excite, batches=camera.batches,
                                    emission_bands=emit)
    elif grid is not None and not isinstance(grid, FluenceGrid):
        raise TypeError(f"grid must be a FluenceGrid, got {type(grid).__name__}")
    elif grid is not None and grid.batches != camera.batches:
        raise ValueError(f"grid.batches = {grid.batches}; allowed the camera's batches ({camera.batches})")
    timings = {"launches": 0.0, "sites": 0.0, "paths": 0.0}
    shape = (camera.batches, scene.tissue.bands.num_bands, camera.height, camera.width)
    sums = np.zeros(shape)
    dsums = np.zeros((camera.batches, len(tangents)) + shape[1:]) if tangents else None
    fluence = dfluence = first = None
    if lights is None or excite:  # the lights' pass: scattered light by next-event estimation, and/or the fluence
        spec = ImageSpec(camera=camera, lobe=lobe and lights is None, grid=grid if excite else None, scatter=lights is None)
        for c, start in enumerate(range(0, photons, chunk_photons)):
            n = min(chunk_photons, photons - start)
            t0 = time.perf_counter()
            done = (lambda k, s=start: progress(s + k)) if progress is not None else None
            out = trace_spectral(scene, key=jax.random.fold_in(key, c), photons=n, options=light_roulette(options),
                                 spectral=spectral, image=spec, progress=done, tangents=tangents)
            timings["launches"] += time.perf_counter() - t0
            first = first or out
            sums = sums + out.image * (n / photons)
            dsums = _add(dsums, out.image_tangents, n / photons)
            fluence = _add(fluence, out.fluence, n / photons)
            dfluence = _add(dfluence, out.fluence_tangents, n / photons)
    from_camera = np.zeros_like(sums)
    dfrom_camera = None if dsums is None else np.zeros_like(dsums)
    widths = None
    if carried:
        t0 = time.perf_counter()
        if fluence is not None:
            fluence, widths = smooth_fluence(fluence, grid)
            if dfluence is not None:
                dfluence = smooth_like(dfluence, grid, widths)
        check_range("launched_power", launched_power, unit="the lights' power", low=0.0, low_open=True)
        source = CameraPaths(camera=camera, bands=carried, grid=grid if fluence is not None else None, fluence=fluence,
                             tangents=dfluence, light_scale=jnp.asarray(1.0 / launched_power, jnp.float64))
        traced = trace_spectral(SpectralScene(scene.tissue, source=source, spectrum=scene.spectrum),
                                key=jax.random.fold_in(key, 1 << 20), photons=paths * camera.pixels, options=path_options,
                                spectral=spectral, image=ImageSpec(camera=camera, lobe=False, lights=lights), tangents=tangents)
        # trace_spectral normalises per path; a pixel's value is the mean of its own paths
        from_camera = traced.image * camera.pixels
        if dfrom_camera is not None:
            dfrom_camera = traced.image_tangents * camera.pixels
        first = first or traced
        timings["paths"] = time.perf_counter() - t0
    return ImageResult(batches=sums + from_camera, photons=photons, sites=(), emitted=(), untraced=0.0,
                       trace=dataclasses.replace(first, image=None, image_tangents=None, fluence=None, fluence_tangents=None),
                       timings=timings, tangent_batches=None if dsums is None else dsums + dfrom_camera,
                       fluorescence_batches=from_camera if lights is None else None, camera_batches=from_camera,
                       grid=grid, paths=paths, grid_smoothing=widths)
