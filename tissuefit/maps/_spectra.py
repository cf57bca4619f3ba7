"""Per-pixel optics: the top layer's (mua, mus, g) per band as a cheap function of the free coefficients.

`PixelSpectra` decomposes the layer's spectral models (tissuefit/scene/_optics.py,
_fluorophores.py) once, before `jit`, into bases on the band grid:

    mua_j = f S A_ox,j + f (1 - S) A_de,j      Blood without packaging (linear in f S and f (1 - S);
                                               band averages commute with the linear model)
          + c (d sigma_f,j)                    each Fluorophore (mua_f = d c sigma_f; its emission:
                                               `conversion`, Y s_jk mua_f,j)
          + mua basis_j                        each ConstantAbsorption
          + conc (ln 10 eps_j)                 each TabulatedAbsorber
    mus'_j = a sum_k W_jk (lambda_jk / 500 nm)^-b   PowerLawScattering (the band's own quadrature)
    mus_j = mus'_j / (1 - g)

so that a pixel's evaluation costs a few vector operations, not the spectral models' table
interpolations. `reference_properties` evaluates the scene's own models (`Layout.tissue` then
`SpectralTissue.properties`), the slow reference the fast path is tested against. Models the
decomposition does not cover (vessel packaging, band overrides, ConstantScattering given per band
with a free mus) make `PixelSpectra` refuse, naming the model.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..fit import FitParameter, Layout, scene_parameters
from ..scene import (
    Blood,
    ConstantAbsorption,
    ConstantScattering,
    Fluorophore,
    PowerLawScattering,
    TabulatedAbsorber,
    emission_spectrum,
    violet_led,
)

GAUSS_POINTS = 4
"""Nodes per band of the power law's quadrature (`gauss_rule`)."""


def gauss_rule(nodes: np.ndarray, weights: np.ndarray, points: int) -> tuple[np.ndarray, np.ndarray]:
    """Per band, the `points`-node Gauss rule of the band's own quadrature (nodes [bands, K], weights
    [bands, K] summing to 1): exact for polynomials of degree < 2 points against the band's response
    (Golub & Welsch, Math Comp 23:221, 1969, on the discrete measure; Stieltjes recurrence). The
    power law (lambda/500)^-b is smooth over a band, so its band average from 4 nodes agrees with the
    full quadrature to ~1e-13 relative, at a fraction of the cost per pixel."""
    out_x = np.zeros((nodes.shape[0], points))
    out_w = np.zeros((nodes.shape[0], points))
    for b in range(nodes.shape[0]):
        use = weights[b] > 0
        x, w = nodes[b][use], weights[b][use]
        m = min(points, x.size)
        centre = float((w * x).sum())
        half = max(float(np.abs(x - centre).max()), 1e-12)
        t = (x - centre) / half  # scaled to [-1, 1] for a well-conditioned recurrence
        alpha, beta = np.zeros(m), np.zeros(m)
        p_prev, p = np.zeros_like(t), np.ones_like(t)
        norm_prev, norm = 1.0, float((w * p * p).sum())
        for k in range(m):
            alpha[k] = float((w * t * p * p).sum()) / norm
            if k:
                beta[k] = norm / norm_prev
            p_next = (t - alpha[k]) * p - (beta[k] if k else 0.0) * p_prev
            p_prev, p = p, p_next
            norm_prev, norm = norm, float((w * p * p).sum())
        jacobi = np.diag(alpha) + np.diag(np.sqrt(beta[1:]), 1) + np.diag(np.sqrt(beta[1:]), -1)
        theta, vec = np.linalg.eigh(jacobi)
        out_x[b, :m] = centre + half * theta
        out_w[b, :m] = vec[0] ** 2 * float(w.sum())
        out_x[b, m:] = centre
    return out_x, out_w


PAIR_FLOOR = 1e-4
"""Relative floor of the band pairs the fluorescence model evaluates (`PixelSpectra.pairs`)."""

ALIASES = {"saturation": "blood_saturation", "ppix": "c_ppix"}
"""Short names `--free` accepts beside the fit's (`saturation` for `blood_saturation`)."""


VIOLET_FWHM_NM = 20.0
"""FWHM [nm] of the PDD camera's violet LED that `violet_light` (and `tissuefit map --light violet`) assumes."""


def violet_light(bands) -> np.ndarray:
    """[bands] a PDD camera's violet light per band, peak band 1: `tissuefit.scene.violet_led` at
    `VIOLET_FWHM_NM` (a 405 nm LED), no other light, so that the red bands see fluorescence alone.
    The `light` of `map` for such a stack."""
    p = np.asarray(violet_led(fwhm_nm=VIOLET_FWHM_NM).band_power(bands), np.float64)
    return p / p.max()


def free_parameters(tissue, names) -> list[FitParameter]:
    """FitParameters of the top layer named by `names` (bare fields or `layer0.<field>`; aliases in
    `ALIASES`); a `ValueError` names what is available."""
    table = {k: p for k, p in scene_parameters(tissue).items() if k.startswith("layer0.")}
    out = []
    for raw in names:
        name = raw.strip()
        name = ALIASES.get(name, name)
        full = name if name.startswith("layer0.") else f"layer0.{name}"
        if full not in table:
            available = ", ".join(k.split(".", 1)[1] for k in table) or "(none)"
            raise ValueError(f"free = {raw!r} is not a coefficient of the top layer's spectral models; "
                             f"available: {available}")
        out.append(table[full])
    if len({p.name for p in out}) != len(out):
        raise ValueError(f"free names a parameter twice: {[p.name for p in out]}")
    if not out:
        raise ValueError("free: at least one parameter is required")
    return out


class PixelSpectra(eqx.Module):
    """The top layer's optics as a function of the free values (module docstring). Static config."""

    names: tuple[str, ...] = eqx.field(static=True)
    """Free fields, in order (e.g. "blood_fraction")."""
    fixed: tuple = eqx.field(static=True)
    """Every other field's (name, value) (floats; a tuple, hashable: part of the compiled program's key)."""
    terms: tuple = eqx.field(static=True)
    """(kind, fields, basis index) per absorption term."""
    bases: np.ndarray
    fluorophores: tuple = eqx.field(static=True)
    """(field, basis index) per fluorophore, in the order of `emission`."""
    emission: np.ndarray
    """[F, bands, bands]: quantum yield x emission share s_jk per fluorophore (`conversion`)."""
    pairs: tuple = eqx.field(static=True)
    """((excitation j, ...), (emission k, ...)): the band pairs some fluorophore converts between:
    those whose mua_f,j Y s_jk at c = 1 is at least `PAIR_FLOOR` of the fluorophore's largest (the
    model EEMs' Gaussian tails reach every pair; on collagen and PpIX the pairs left out carry 6e-5
    of the converted light); with a `light`, the floor applies to light_j mua_f,j Y s_jk."""
    log_nodes: np.ndarray
    weights: np.ndarray
    scattering: str = eqx.field(static=True)

    def __init__(self, tissue, parameters, light=None):
        """`light` [bands] or [stacks, bands] (optional): the illumination per band (of each stack);
        pairs that no light excites at `PAIR_FLOOR` of a fluorophore's strongest pair or more are not
        evaluated (a violet PDD light leaves the pairs excited near 405 nm)."""
        optics = tissue.layers[0]
        if optics.override is not None:
            raise ValueError("per-pixel maps: layer 0 has a BandOverride; the per-pixel model covers Blood, "
                             "Fluorophore, ConstantAbsorption, TabulatedAbsorber and Power-law/Constant scattering")
        bands = tissue.bands
        table = {k.split(".", 1)[1]: p for k, p in scene_parameters(tissue).items() if k.startswith("layer0.")}
        self.names = tuple(p.name.split(".", 1)[1] for p in parameters)
        fixed = {k: float(np.asarray(p.where(tissue)).reshape(-1)[0]) for k, p in table.items()
                 if k not in self.names and np.asarray(p.where(tissue)).size == 1}
        terms, bases, fluorophores, emission = [], [], [], []
        n_const = n_tab = 0
        seen = set()
        for ab in optics.absorbers:
            if isinstance(ab, Blood):
                if "blood" in seen:
                    raise ValueError("per-pixel maps: layer 0 has two Blood absorbers; give it one")
                seen.add("blood")
                if float(np.asarray(ab.vessel_radius)) != 0.0:
                    raise ValueError(f"per-pixel maps: blood.vessel_radius = {float(ab.vessel_radius):g} cm; the "
                                     "per-pixel model needs 0 (no packaging: linear in fraction and saturation)")
                h = ab.hemoglobin
                bases += [np.asarray(Blood(1.0, 1.0, hemoglobin=h).absorption(bands)),
                          np.asarray(Blood(1.0, 0.0, hemoglobin=h).absorption(bands))]
                terms.append(("blood", ("blood_fraction", "blood_saturation"), len(bases) - 2))
            elif isinstance(ab, Fluorophore):
                short = {"protoporphyrin_ix": "ppix"}.get(ab.name, ab.name)
                bases.append(np.asarray(ab.d * ab.specific_absorption))
                terms.append(("linear", (f"c_{short}",), len(bases) - 1))
                fluorophores.append((f"c_{short}", len(bases) - 1))
                emission.append(float(np.asarray(ab.quantum_yield)) * np.asarray(emission_spectrum(ab.eem)))
                fixed.setdefault(f"c_{short}", float(np.asarray(ab.c)))
                if short != ab.name:
                    fixed.pop(f"c_{ab.name}", None)
            elif isinstance(ab, ConstantAbsorption):
                name = "mua" if n_const == 0 else f"mua{n_const}"
                n_const += 1
                mua = np.asarray(ab.mua, np.float64)
                if mua.ndim == 0:
                    bases.append(np.ones(bands.num_bands))
                    terms.append(("linear", (name,), len(bases) - 1))
                else:
                    if name in self.names:
                        raise ValueError(f"per-pixel maps: {name} is given per band; a free mua must be one value")
                    bases.append(mua)
                    terms.append(("constant", (), len(bases) - 1))
            elif isinstance(ab, TabulatedAbsorber):
                bases.append(np.asarray(ab.absorption(bands)) / max(float(ab.concentration), 1e-300)
                             if float(ab.concentration) > 0 else
                             np.asarray(TabulatedAbsorber(ab.wavelengths, ab.extinction, 1.0).absorption(bands)))
                terms.append(("linear", (f"conc_{n_tab}",), len(bases) - 1))
                n_tab += 1
            else:
                raise ValueError(f"per-pixel maps: layer 0 absorber {type(ab).__name__} is not covered by the per-pixel model")
        sc = optics.scattering
        nodes, weights = bands.quadrature()
        if isinstance(sc, PowerLawScattering):
            self.scattering = "power"
        elif isinstance(sc, ConstantScattering):
            if np.asarray(sc.mus).ndim or np.asarray(sc.g).ndim:
                raise ValueError("per-pixel maps: ConstantScattering given per band; give one mus and one g")
            self.scattering = "constant"
        else:
            raise ValueError(f"per-pixel maps: scattering {type(sc).__name__} is not covered by the per-pixel model")
        self.fixed = tuple(sorted(fixed.items()))
        self.terms = tuple(terms)
        self.fluorophores = tuple(fluorophores)
        self.emission = np.asarray(emission, np.float64).reshape(len(emission), bands.num_bands, bands.num_bands)
        self.bases = np.asarray(bases, np.float64).reshape(len(bases), bands.num_bands)
        reach = np.zeros((bands.num_bands, bands.num_bands), bool)
        for f, (_, k) in enumerate(self.fluorophores):
            m = self.bases[k][:, None] * self.emission[f]
            for lit in [None] if light is None else np.atleast_2d(np.asarray(light, np.float64)):
                ml = m if lit is None else lit[:, None] * m
                reach |= (ml > 0) & (ml >= PAIR_FLOOR * ml.max())
        j, k = np.nonzero(reach)
        self.pairs = (tuple(int(i) for i in j), tuple(int(i) for i in k))
        gauss_nodes, gauss_weights = gauss_rule(nodes, weights, GAUSS_POINTS)
        self.log_nodes = np.log(gauss_nodes / PowerLawScattering.REFERENCE_NM)
        self.weights = gauss_weights

    def value(self, free, name):
        return free[self.names.index(name)] if name in self.names else dict(self.fixed)[name]

    def properties(self, free):
        """(mua [bands], mus [bands], g) of the top layer at the free values `free` [len(names)]."""
        mua = 0.0
        bases = jnp.asarray(self.bases)
        for kind, fields, k in self.terms:
            if kind == "blood":
                f, s = self.value(free, fields[0]), self.value(free, fields[1])
                mua = mua + f * s * bases[k] + f * (1.0 - s) * bases[k + 1]
            elif kind == "linear":
                mua = mua + self.value(free, fields[0]) * bases[k]
            else:
                mua = mua + bases[k]
        mua = mua + jnp.zeros(self.bases.shape[1])
        g = self.value(free, "g")
        if self.scattering == "power":
            a, b = self.value(free, "a"), self.value(free, "b")
            mus_r = a * jnp.sum(jnp.asarray(self.weights) * jnp.exp(-b * jnp.asarray(self.log_nodes)), -1)
            mus = mus_r / (1.0 - g)
        else:
            mus = self.value(free, "mus") + jnp.zeros(self.bases.shape[1])
        return mua, mus, g


    def conversion(self, free):
        """M [P] at `pairs`: escaping fluorescence in band k per unit I_jk (`WhiteModel.log_fluorescence`)
        and unit incident power in band j, summed over the fluorophores: sum_f Y_f s_f,jk mua_f,j."""
        j, k = (np.asarray(p, np.int32) for p in self.pairs)
        bases = jnp.asarray(self.bases)
        m = 0.0
        for f, (field, b) in enumerate(self.fluorophores):
            m = m + self.value(free, field) * bases[b][j] * jnp.asarray(self.emission[f][j, k])
        return m


def reference_properties(tissue, parameters, free_values):
    """The reference: the scene's own spectral models with the free values set (`Layout.tissue`
    through the parameters' transforms' identity), (mua, mus, g) of the top layer per band."""
    layout = Layout(tuple(parameters), tuple(() for _ in parameters))
    x = jnp.asarray([p.to_unconstrained(v) for p, v in zip(parameters, free_values)])
    t = layout.tissue(tissue, x)
    mua, mus, g = t.properties()
    return mua[0], mus[0], g[0]
