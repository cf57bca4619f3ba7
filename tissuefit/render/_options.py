"""`RenderOptions`: how a render estimates the radiance the camera sees (static configuration)."""

from __future__ import annotations

from typing import Literal

import equinox as eqx

from .._checks import check_positive_int, check_range
from ..photonmap import KERNELS

Estimator = Literal["nee", "adjoint", "photon-map"]
ESTIMATORS: tuple[str, ...] = ("nee", "adjoint", "photon-map")


class RenderOptions(eqx.Module):
    """How a render estimates radiance (static: changing it recompiles).

    `estimator`: "nee" (default), "adjoint" or "photon-map".
    - "nee": next-event estimation to the camera (`tissuefit.transport.trace_image`): every
      interaction scores the light it sends straight to the camera, unbiased and without kernels;
      fluorescence from emission sites traced as photons of their own. It measured the lowest error
      per second (experiments/render/RESULTS.md). Options: `batches` (independent images the photons
      are split into, for the variance), `splits` (photons per emission site), `site_rate`
      (emission sites per interaction where a band's strongest emitter is), `lobe` (default on:
      also score a vertex sampled towards the camera at every scattering and emission, by multiple
      importance sampling; against a converged reference it cut the smoothed image's error 1.3-2.8x
      per band group at equal launches, for about 1.4x the time), `smoothing`: "sure"
      (default: a Gaussian per band whose width minimises Stein's unbiased estimate of the squared
      error, `_denoise.py`) or "none"; `smoothing_px` fixes the width instead [pixels].
      `nee_fluorescence`: "adjoint" (default) traces fluorescence from the camera: the launches
      tally the excitation fluence into a grid, then `paths` paths per pixel (default 16) start
      from the camera and score the fluorescence source it holds (`tissuefit.transport._adjoint`;
      no phase function towards a pinhole, so no heavy tail; the grid adds an O(h^2) bias). On the
      paper's lesion at 128 x 128 it cut the fluorescence groups' error 6-8x at equal time against
      "sites", which traces it from emission sites on the lights' side (`splits`, `site_rate`;
      experiments/render/RESULTS.md).
    - "adjoint": everything from the camera: `paths` paths per pixel connect to the endoscope's
      lights (light sampling and their own flights, by multiple importance sampling:
      `tissuefit.transport._lights`) and score fluorescence as "nee" with "adjoint" fluorescence
      does; the lights' launches only tally the excitation fluence (none are traced without
      fluorophores). Cone lights only (a collimated flood cannot be hit by a path). `batches`,
      `smoothing` as for "nee".
    - "photon-map": the paper's method (Zacher 2009): a surface photon map for the light leaving
      the tissue, spread by an angular model, and an S-step ray march through volume maps for
      fluorescence. Options:
      - `steps`: ray-marching steps S (the paper: 5); `step_length` [cm]: dx (default 1 / the
        smallest mut of the top layer over the lit bands, one mean free path).
      - `kernel`: density kernel (`tissuefit.photonmap.KERNELS`; default Epanechnikov).
      - `surface_radius`, `volume_radius` [cm]: fixed bandwidths (default: from the records, the
        median distance to the k-th nearest record over the pixels / march points, k =
        `neighbours` at 1e5 records growing as N^(2/3) on the surface, N^(4/7) in the volume;
        `_bandwidth.py`); `k`: an adaptive k-nearest-record bandwidth instead (the paper's
        estimate is `kernel="box", k=...`), capped at the radius.
      - `fluorescence`: "march" (from the volume maps, the paper's) or "surface" (from the surface
        map with the angular model; no volume map).
      - `angular`: "fresnel" (default) or "lambertian": the surface term's angular model.
      - `volume_capacity`: volume records to keep per launched photon before retrying larger.
    Both:
    - `specular_deg`: the specular lobe's sigma [deg] (0: no specular term).
    - `halton`: launch from scrambled Halton points (the paper's) instead of pseudo-random ones.
    - `margin` [cm]: launches landing farther than this outside the camera's view are not traced.
    """

    estimator: Estimator = eqx.field(static=True, default="nee")
    batches: int = eqx.field(static=True, default=16)
    splits: int = eqx.field(static=True, default=1)
    site_rate: float = eqx.field(static=True, default=0.1)
    lobe: bool = eqx.field(static=True, default=True)
    smoothing: Literal["sure", "none"] = eqx.field(static=True, default="sure")
    smoothing_px: float | None = eqx.field(static=True, default=None)
    nee_fluorescence: Literal["adjoint", "sites"] = eqx.field(static=True, default="adjoint")
    paths: int = eqx.field(static=True, default=16)
    steps: int = eqx.field(static=True, default=5)
    step_length: float | None = eqx.field(static=True, default=None)
    kernel: str = eqx.field(static=True, default="epanechnikov")
    surface_radius: float | None = eqx.field(static=True, default=None)
    volume_radius: float | None = eqx.field(static=True, default=None)
    k: int | None = eqx.field(static=True, default=None)
    neighbours: int = eqx.field(static=True, default=48)
    fluorescence: Literal["march", "surface"] = eqx.field(static=True, default="march")
    angular: Literal["fresnel", "lambertian"] = eqx.field(static=True, default="fresnel")
    specular_deg: float = eqx.field(static=True, default=4.0)
    halton: bool = eqx.field(static=True, default=True)
    margin: float = eqx.field(static=True, default=0.3)
    volume_capacity: float = eqx.field(static=True, default=6.0)

    def __check_init__(self):
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"render.estimator = {self.estimator!r}; allowed 'nee', 'adjoint' or 'photon-map'")
        check_positive_int("render.batches", self.batches, high=4096)
        if self.estimator != "photon-map" and self.batches < 2:
            raise ValueError(f"render.batches = {self.batches}; allowed 2 .. 4096 (the variance needs two batches)")
        check_positive_int("render.splits", self.splits, high=1024)
        if not isinstance(self.lobe, bool):
            raise TypeError(f"render.lobe = {self.lobe!r}; allowed True or False")
        check_range("render.site_rate", self.site_rate, unit="sites per interaction", low=0.0, high=1.0, low_open=True)
        if self.smoothing not in ("sure", "none"):
            raise ValueError(f"render.smoothing = {self.smoothing!r}; allowed 'sure' or 'none'")
        if self.nee_fluorescence not in ("adjoint", "sites"):
            raise ValueError(f"render.nee_fluorescence = {self.nee_fluorescence!r}; allowed 'adjoint' or 'sites'")
        check_positive_int("render.paths", self.paths, high=1 << 20)
        if self.smoothing_px is not None:
            check_range("render.smoothing_px", self.smoothing_px, unit="pixels", low=0.0, high=64.0)
        check_positive_int("render.steps", self.steps, high=1000)
        for name in ("step_length", "surface_radius", "volume_radius"):
            if getattr(self, name) is not None:
                check_range(f"render.{name}", getattr(self, name), unit="cm", low=0.0, low_open=True)
        if self.kernel not in KERNELS:
            raise ValueError(f"render.kernel = {self.kernel!r}; allowed one of {', '.join(map(repr, KERNELS))}")
        if self.k is not None:
            check_positive_int("render.k", self.k, high=2**20)
        check_positive_int("render.neighbours", self.neighbours, high=2**20)
        if self.fluorescence not in ("march", "surface"):
            raise ValueError(f"render.fluorescence = {self.fluorescence!r}; allowed 'march' or 'surface'")
        if self.angular not in ("fresnel", "lambertian"):
            raise ValueError(f"render.angular = {self.angular!r}; allowed 'fresnel' or 'lambertian'")
        check_range("render.specular_deg", self.specular_deg, unit="deg", low=0.0, high=45.0)
        check_range("render.margin", self.margin, unit="cm", low=0.0)
        check_range("render.volume_capacity", self.volume_capacity, unit="records per photon", low=0.0, low_open=True)
        if not isinstance(self.halton, bool):
            raise TypeError(f"render.halton = {self.halton!r} must be True or False")
