"""Differentiable tallies: trace at the current parameters, write the tallies as explicit functions.

`tallies` (single band, `Scene`): the tracer accumulates, per tally bin, the weighted path
statistics that give the likelihood-ratio derivatives (`PathStats`); the tallies come back in the
detached form T(theta) = T0 + J (theta - stop_gradient(theta)): equal to the traced values, with
the pMC Jacobian J as their derivative in forward and reverse mode.

`trace_records` (spectral, `SpectralScene`): every photon escaping through the top is a record
(a buffer as large as the photon count cannot overflow), replayed exactly (`RecordReplay`): rd and
the escaping fluorescence per band at any nearby tissue, with derivatives and an effective sample size.

Both trace eagerly (outside `jax.jit`); the functions they return are jit-able.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import is_concrete
from .._setup import float64
from ..scene import Scene, SpectralScene, SpectralTissue
from ..transport import TALLY_NAMES, RecordSpec, SpectralOptions, TallySpec, TraceOptions, trace, trace_spectral
from ._records import RecordReplay

DIFFERENTIABLE = ("mua", "mus", "g")
"""Per-layer (per-medium, per-band) coefficients the likelihood ratio differentiates."""

NOT_DIFFERENTIABLE = ("n", "thickness", "n_above", "n_below")
"""Geometry: moving a face or changing an index changes which paths escape (boundary terms the
likelihood ratio does not see). Asking for their derivative is an error, never a silent zero."""

JACOBIAN_TALLIES = ("rd", "tt", "a") + TALLY_NAMES


def _is_tracer(x) -> bool:
    return isinstance(x, jax.core.Tracer)


REGION_GEOMETRY = ("center", "radius", "lower", "upper")
"""Region fields that place a lesion (not differentiable, like the layers' faces)."""


def _refuse_geometry(tissue, where: str) -> None:
    geometry = tissue.geometry if isinstance(tissue, SpectralTissue) else tissue
    for k, region in enumerate(getattr(tissue, "regions", ())):
        for name in REGION_GEOMETRY:
            if _is_tracer(getattr(region, name, None)):
                raise ValueError(
                    f"{where}: tissue.regions[{k}].{name} is being differentiated or traced; a lesion's "
                    "position and size are not differentiable (they move boundaries). Its optics and "
                    "concentrations are."
                )
    for name in NOT_DIFFERENTIABLE:
        if _is_tracer(getattr(geometry, name)):
            raise ValueError(
                f"{where}: tissue.{name} is being differentiated or traced; it is not differentiable "
                f"(boundary terms the likelihood ratio misses). Differentiate with respect to "
                f"{', '.join(DIFFERENTIABLE)} (or the spectral models' coefficients) only, e.g. by closing over {name}"
            )


def _concrete(tree, where: str):
    """The primal values of `tree` (stop_gradient); they must be numbers, not jit tracers."""
    values = jax.tree.map(jax.lax.stop_gradient, tree)
    if not all(is_concrete(leaf) for leaf in jax.tree.leaves(values)):
        raise ValueError(f"{where} traces photons eagerly: call it outside jax.jit (grad, jacfwd, jvp, vmap of the result are fine)")
    return values


@float64
def tallies(scene: Scene, *, key, photons: int, tallies: TallySpec = TallySpec(names=()),
            options: TraceOptions = TraceOptions(), **trace_kwargs) -> dict:
    """Trace `scene` and return its tallies as differentiable functions of `scene.tissue`'s mua, mus, g.

    Returns a dict: "rd", "tt", "a" (always), and every resolved tally in `tallies.names` (rd_r, rd_a,
    rd_ra, tt_r, tt_a, tt_ra, a_z, a_rz, a_layer, in `TraceResult`'s units), each a JAX array equal to the traced tally
    whose derivative with respect to the layers' mua,
    mus, g [1/cm, 1/cm, -] is the likelihood-ratio (pMC) derivative, plus "result": the
    `TraceResult` (numpy; standard errors there). Keyword arguments go to `trace`.
    Works under `jax.grad`, `jax.jacfwd`, `jax.jacrev`, `jax.jvp` (not `jit`: it traces eagerly).
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a tissuefit.Scene, got {type(scene).__name__}")
    unsupported = [n for n in tallies.names if n not in JACOBIAN_TALLIES]
    if unsupported:
        raise ValueError(f"tallies.names: {unsupported[0]!r} has no path statistics; differentiable tallies are {list(JACOBIAN_TALLIES)}")
    scene0 = _concrete(scene, "replay.tallies")
    _refuse_geometry(scene.tissue, "replay.tallies")
    if any(_is_tracer(leaf) for leaf in jax.tree.leaves(scene.source)):
        raise ValueError("replay.tallies: the source is not differentiable (its geometry moves paths)")
    result = trace(scene0, key=key, photons=photons, tallies=tallies,
                   options=dataclasses.replace(options, path_stats=True), **trace_kwargs)
    t, t0 = scene.tissue, scene0.tissue
    delta = {name: jnp.asarray(getattr(t, name), jnp.float64) - jnp.asarray(getattr(t0, name), jnp.float64)
             for name in DIFFERENTIABLE}
    out = {}
    for name in ("rd", "tt", "a") + tuple(tallies.names):
        jac = result.jacobian(name)
        value = jnp.asarray(getattr(result, name), jnp.float64)
        for p in DIFFERENTIABLE:
            value = value + jnp.asarray(jac[p]) @ delta[p]
        out[name] = value
    out["result"] = result
    return out


class EscapeReplay(eqx.Module):
    """The top-surface records of a spectral trace, replayable at nearby tissues (`trace_records`).

    - `replay`: the `RecordReplay` (records and the traced tissue); `result`: the `SpectralResult`.
    - `rd(tissue)`, `rd_fluor(tissue)`: diffuse reflectance and its fluorescence part per band [bands]
      at `tissue`, explicit (jit, grad, jacfwd); at the traced tissue they equal the trace's tallies.
    - `effective_sample_size(tissue)`: per band, relative to the trace (re-trace when it drops).
    """

    replay: RecordReplay
    result: object

    @float64
    def rd(self, tissue: SpectralTissue):
        return self.replay.power(tissue).sum(0)

    @float64
    def rd_fluor(self, tissue: SpectralTissue):
        converted = jnp.asarray(self.replay.records.converted)[:, None]
        return jnp.where(converted, self.replay.power(tissue), 0.0).sum(0)

    @float64
    def effective_sample_size(self, tissue: SpectralTissue):
        return self.replay.effective_sample_size(tissue)

    @property
    def untracked(self):
        return self.replay.untracked


@float64
def trace_records(scene: SpectralScene, *, key, photons: int, options: TraceOptions = TraceOptions(),
                  spectral: SpectralOptions = SpectralOptions(), **trace_kwargs) -> EscapeReplay:
    """Trace `scene` keeping every escaping photon as a replayable record; returns an `EscapeReplay`.

    Shared paths where the scene allows them (`spectral.mode`), fluorescent scenes included: a
    converted record keeps the band weights its emission mixed. Outside `jax.jit`; the tissue's
    values are read with stop_gradient, so this may be called inside a function being differentiated.
    """
    if not isinstance(scene, SpectralScene):
        raise TypeError(f"scene must be a tissuefit.SpectralScene, got {type(scene).__name__}")
    scene0 = _concrete(scene, "replay.trace_records")
    _refuse_geometry(scene.tissue, "replay.trace_records")
    result = trace_spectral(scene0, key=key, photons=photons, options=options, spectral=spectral,
                            records=RecordSpec(surface=photons, replay=True), **trace_kwargs)
    records = result.surface_records
    if records.overflow:  # pragma: no cover - one escape per photon at most
        raise RuntimeError(f"trace_records: {records.overflow} surface records dropped")
    return EscapeReplay(replay=RecordReplay(records, scene0.tissue), result=dataclasses.replace(result, surface_records=None))


__all__ = ["tallies", "trace_records", "EscapeReplay"]
