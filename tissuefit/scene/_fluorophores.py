"""Fluorophores: absorption, excitation–emission matrices (EEMs) and the conversion they cause.

Built in: collagen (healthy mucosa's dominant autofluorescence) and protoporphyrin IX (PpIX,
accumulated by tumours), both parametric band models on the band grid; user EEMs come from a
plain-text matrix file (`read_eem` / `write_eem`). How a fluorophore's d, c, quantum yield and EEM
become a conversion probability and an emission spectrum is set out in `Fluorophore` and in
tissuefit/data/SOURCES.md; the pure functions `emission_spectrum`, `conversion_probability` and
`conversion_matrix` compute it from arrays.
"""

from __future__ import annotations

import functools
import importlib.resources
import os
from typing import Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._atomic import atomic_writer
from .._checks import check_range, f64
from ._optics import LN10, AbstractAbsorber, LayerOptics
from ._spectra import DEFAULT_BANDS, BandGrid, _check_increasing, _parse_csv, _parse_float

PPIX_REFERENCE_CONCENTRATION = 10e-6
"""PpIX concentration [M] that c = 1 stands for (10 µM, about 5.6 µg/g: high ALA-induced tumour levels)."""

Quantity = Literal["photons", "energy"]


# ---------------------------------------------------------------------------------------------
# Pure functions: the conversion model
# ---------------------------------------------------------------------------------------------


def stokes_mask(num_bands: int) -> np.ndarray:
    """[bands, bands] 0/1 mask, 1 where emission band j ≥ excitation band i (bands in increasing λ)."""
    return np.triu(np.ones((num_bands, num_bands)))


def emission_spectrum(eem: Float[Array, "bands bands"]) -> Float[Array, "bands bands"]:
    """Emission spectrum per excitation band: s[i, j] = EEM[i, j] / Σ_j' EEM[i, j'] over j ≥ i.

    Rows sum to 1 (a converted photon is emitted somewhere in the grid) except rows whose Stokes
    part is all zero, which are all zero (that band converts nothing). Entries j < i are zero
    (Stokes: emission only at longer wavelengths). Differentiable in `eem`.
    """
    eem = jnp.asarray(eem) * jnp.asarray(stokes_mask(eem.shape[-1]))
    total = jnp.sum(eem, axis=-1, keepdims=True)
    safe = jnp.where(total > 0, total, 1.0)
    return jnp.where(total > 0, eem / safe, 0.0)


def fluorophore_absorption(specific_absorption, d, c) -> Float[Array, " bands"]:
    """mua_f [1/cm] = d · c · σ_f: `specific_absorption` σ_f [1/cm] at d = c = 1, `d`, `c` [-]."""
    return d * c * specific_absorption


def conversion_probability(mua_fluorophore, mua, mus, quantum_yield) -> Float[Array, " bands"]:
    """Probability that an interaction in band i converts the photon: φ · mua_f,i / (mua_i + mus_i).

    Arguments ([bands] or broadcastable): `mua_fluorophore` mua_f [1/cm], this fluorophore's
    absorption; `mua` [1/cm], the layer's *total* absorption (including mua_f); `mus` [1/cm];
    `quantum_yield` φ [-]. In MCML's weighted form: of a packet of weight W, the drop step
    deposits W·mua/mut, and W·φ·mua_f/mut of it is re-emitted. Differentiable in all arguments.
    """
    return quantum_yield * mua_fluorophore / (mua + mus)


def conversion_matrix(
    mua_fluorophore,
    mua,
    mus,
    quantum_yield,
    eem,
    *,
    wavelengths=None,
    quantity: Quantity = "photons",
) -> Float[Array, "bands bands"]:
    """P[i, j]: weight moved from excitation band i to emission band j per unit weight at an interaction.

    P[i, j] = φ · mua_f,i / (mua_i + mus_i) · s[i, j], s = `emission_spectrum(eem)`.
    With `quantity="energy"` (weights are radiant power, not photon counts) each entry is also
    multiplied by λ_i / λ_j (Stokes energy loss); `wavelengths` [bands] (nm) is then required.
    Arguments as for `conversion_probability`. Differentiable in all array arguments.
    """
    p = conversion_probability(mua_fluorophore, mua, mus, quantum_yield)
    m = p[..., :, None] * emission_spectrum(eem)
    if quantity == "energy":
        if wavelengths is None:
            raise ValueError("conversion_matrix: quantity='energy' needs the band wavelengths [nm]")
        wl = jnp.asarray(wavelengths, dtype=jnp.float64)
        m = m * (wl[:, None] / wl[None, :])
    elif quantity != "photons":
        raise ValueError(f"quantity = {quantity!r} is not one of 'photons', 'energy'")
    return m


# ---------------------------------------------------------------------------------------------
# The Module
# ---------------------------------------------------------------------------------------------


class Fluorophore(AbstractAbsorber):
    """A fluorophore in a layer: its absorption adds to the layer's mua; absorbed photons may re-emit.

    Fields:
    - `name`: static label.
    - `bands`: the static `BandGrid` its spectra live on.
    - `specific_absorption`: σ_f,i [1/cm], ≥ 0, [bands]: band-averaged absorption of the
      fluorophore-bearing compartment at d = c = 1 (data; a leaf, normally frozen).
    - `eem`: [bands (excitation), bands (emission)], ≥ 0, relative units; entries with emission
      band j < excitation band i are set to zero on construction (Stokes). Data, normally frozen.
    - `d`: the paper's "probability of interaction of a photon with the fluorophore" [-], in
      [0, 1]. Differentiable.
    - `c`: the paper's "concentration of fluorescent molecules in the fluorophore" [-], ≥ 0,
      relative to the fluorophore's reference concentration (PpIX: c = 1 ⇔ 10 µM). Differentiable.
    - `quantum_yield`: φ [-], in [0, 1], photons emitted per photon absorbed. Differentiable.

    The model (Zacher 2009 §3 lists d and c without an equation; this is our reading, see
    tissuefit/data/SOURCES.md for the argument):

    1. Absorption. d is the fraction of interaction sites that lie in the fluorophore-bearing
       compartment (collagen fibres in the stroma, PpIX-laden cells), c the concentration of
       fluorescent molecules there, σ_f their absorption per unit c. The fluorophore adds

           mua_f,i = d · c · σ_f,i                                  [1/cm]

       to the layer's absorption (`absorption`), exactly as blood fraction × blood mua does.
    2. Conversion at an interaction in excitation band i (MCML's drop step): the fraction
       mua_i / mut_i of the weight is absorbed, a share mua_f,i / mua_i of that by the
       fluorophore, and a share φ of those photons is re-emitted:

           p_f,i = φ · mua_f,i / mut_i,    mut_i = mua_i + mus_i, mua_i including mua_f,i

       (per absorbed weight: φ · mua_f,i / mua_i). The rest of the absorbed weight is heat.
    3. Emission over bands j: the EEM row, Stokes-masked and normalised (Kasha: the emission
       shape does not depend on how much was absorbed; the EEM's row *strength* is already in
       σ_f), s_f,ij = EEM_ij / Σ_{j' ≥ i} EEM_ij' for j ≥ i, 0 for j < i. Weight moved from band i
       to band j per unit weight at the interaction: P_f,ij = p_f,i · s_f,ij (photon counts), or
       P_f,ij · λ_i/λ_j if the weights are radiant power.

    Relation to the paper: Zacher 2009 gives no equation for d or c (§3, lines 59–64 of
    references/000_c9388d6e85445eae.txt; §4, lines 72–74: a photon that "hit" a fluorophore has its
    spectrum "updated using EEM"; Fig. 1 caption, line 79: conversion "happens very rarely"). Read
    as a per-interaction absorption probability, d = 0.2 would need mua_f = d · mut = 44 /cm in
    the paper's tissue (mua = 20, mus = 200 /cm), more than its total absorption, and could not
    depend on the excitation band. Read as the compartment fraction above, the paper's d and c
    stand unchanged and conversion is rare, band-dependent and energy-conserving (in the paper's
    tissue, 400 nm band: p = 7.8e-5 for collagen, 4.4e-5 for PpIX).

    Only the products d · c · σ_f and (d · c · σ_f) · φ are identifiable from images when
    mua_f ≪ mua: fit c (in log coordinates) and hold d, σ_f and φ fixed.
    """

    name: str = eqx.field(static=True)
    bands: BandGrid = eqx.field(static=True)
    specific_absorption: Float[Array, " bands"]
    eem: Float[Array, "bands bands"]
    d: Float[Array, ""]
    c: Float[Array, ""]
    quantum_yield: Float[Array, ""]

    def __init__(self, *, name: str, bands: BandGrid, specific_absorption, eem, d, c, quantum_yield):
        if not isinstance(bands, BandGrid):
            raise TypeError(f"fluorophore {name!r}: bands is a {type(bands).__name__}, not a BandGrid")
        n = bands.num_bands
        sigma = f64(specific_absorption)
        eem = f64(eem)
        if sigma.shape != (n,):
            raise ValueError(f"{name}.specific_absorption has shape {sigma.shape}; expected ({n},), one value per band")
        if eem.shape != (n, n):
            raise ValueError(f"{name}.eem has shape {eem.shape}; expected ({n}, {n}) (excitation bands × emission bands)")
        self.name = str(name)
        self.bands = bands
        self.specific_absorption = sigma
        self.eem = eem * stokes_mask(n)
        self.d = f64(d)
        self.c = f64(c)
        self.quantum_yield = f64(quantum_yield)

    def __check_init__(self):
        check_range(f"{self.name}.specific_absorption", self.specific_absorption, unit="1/cm", low=0.0)
        check_range(f"{self.name}.eem", self.eem, unit="-", low=0.0)
        check_range(f"{self.name}.d", self.d, unit="-", low=0.0, high=1.0)
        check_range(f"{self.name}.c", self.c, unit="-", low=0.0)
        check_range(f"{self.name}.quantum_yield", self.quantum_yield, unit="-", low=0.0, high=1.0)

    def _check_bands(self, bands: BandGrid) -> None:
        if bands != self.bands:
            raise ValueError(
                f"{self.name}: its spectra are on a band grid of {self.bands.num_bands} bands "
                f"({self.bands.centers[0]:g}–{self.bands.centers[-1]:g} nm, {self.bands.response}); "
                "build it on the grid the layer is evaluated on"
            )

    def absorption(self, bands: BandGrid) -> Float[Array, " bands"]:
        """mua_f = d · c · σ_f [1/cm] per band."""
        self._check_bands(bands)
        return fluorophore_absorption(self.specific_absorption, self.d, self.c)

    def emission(self) -> Float[Array, "bands bands"]:
        """s[i, j], the normalised Stokes emission spectrum per excitation band (rows sum to 1 or 0)."""
        return emission_spectrum(self.eem)

    def conversion(self, mua, mus, *, quantity: Quantity = "photons") -> Float[Array, "bands bands"]:
        """P[i, j] given the layer's total `mua` and `mus` [1/cm] per band (see `conversion_matrix`)."""
        return conversion_matrix(
            self.absorption(self.bands), mua, mus, self.quantum_yield, self.eem,
            wavelengths=self.bands.wavelengths, quantity=quantity,
        )

    @classmethod
    def from_eem(
        cls,
        bands: BandGrid,
        eem,
        *,
        name: str,
        d,
        c,
        quantum_yield,
        specific_absorption=None,
        peak_absorption=None,
    ) -> Fluorophore:
        """A fluorophore from an EEM on `bands` [excitation, emission].

        Give its absorption either as `specific_absorption` [bands] (1/cm at d = c = 1) or as
        `peak_absorption` [1/cm]: then σ_f,i = peak_absorption · R_i / max R, with R_i the EEM's
        row sums (for a dilute sample an EEM row's total is ∝ absorption × yield, so its shape is
        the excitation spectrum; emission outside the grid is ignored).
        """
        eem = np.asarray(eem, dtype=np.float64)
        if (specific_absorption is None) == (peak_absorption is None):
            raise ValueError(f"{name}: give exactly one of specific_absorption [1/cm per band] or peak_absorption [1/cm]")
        if specific_absorption is None:
            check_range(f"{name}.peak_absorption", peak_absorption, unit="1/cm", low=0.0)
            rows = (eem * stokes_mask(eem.shape[0])).sum(axis=1) if eem.ndim == 2 and eem.shape[0] == eem.shape[1] else None
            if rows is None or not np.all(np.isfinite(rows)) or rows.max() <= 0:
                raise ValueError(
                    f"{name}.eem must be a square, finite matrix with a positive entry to derive the absorption from"
                )
            specific_absorption = float(peak_absorption) * rows / rows.max()
        return cls(
            name=name, bands=bands, specific_absorption=specific_absorption, eem=eem,
            d=d, c=c, quantum_yield=quantum_yield,
        )

    @classmethod
    def from_eem_file(cls, path, bands: BandGrid = DEFAULT_BANDS, **kwargs) -> Fluorophore:
        """`from_eem` with the matrix read by `read_eem` and resampled by `eem_on_bands`."""
        ex, em, matrix = read_eem(path)
        return cls.from_eem(bands, eem_on_bands(bands, ex, em, matrix), **kwargs)


def layer_conversion(
    layer: LayerOptics, bands: BandGrid, *, quantity: Quantity = "photons"
) -> Float[Array, "fluorophores bands bands"]:
    """Conversion matrices P_f[i, j] of every `Fluorophore` among `layer.absorbers`, stacked.

    Uses the layer's own total mua and mus (`layer.properties`), so it is consistent with the
    transport's interaction rates. Shape [fluorophores, bands, bands]; [0, bands, bands] when the
    layer has none. Differentiable in every coefficient of the layer.
    """
    mua, mus, _ = layer.properties(bands)
    mats = [a.conversion(mua, mus, quantity=quantity) for a in layer.absorbers if isinstance(a, Fluorophore)]
    if not mats:
        return jnp.zeros((0, bands.num_bands, bands.num_bands), jnp.float64)
    return jnp.stack(mats)


# ---------------------------------------------------------------------------------------------
# Built-in fluorophores (parametric band models; tissuefit/data/*_model.csv)
# ---------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=8)
def _band_model(filename: str) -> dict[str, list[tuple[float, float, float, float]]]:
    """Gaussian components {"absorption": [(centre, sigma_left, sigma_right, peak)], "emission": […]}."""
    ref = importlib.resources.files("tissuefit").joinpath("data", filename)
    with importlib.resources.as_file(ref) as path:
        header, rows, _ = _parse_csv(path)
        expected = ["component", "center_nm", "sigma_left_nm", "sigma_right_nm", "peak"]
        if header != expected:
            raise ValueError(f"{path}: header must be {','.join(expected)}")
        out: dict[str, list] = {"absorption": [], "emission": []}
        for lineno, fields in rows:
            if len(fields) != 5 or fields[0] not in out:
                raise ValueError(f"{path} line {lineno}: expected absorption|emission and 4 numbers")
            out[fields[0]].append(tuple(_parse_float(path, lineno, header[k], fields[k]) for k in range(1, 5)))
    return out


def _gaussians(components, wavelength: np.ndarray) -> np.ndarray:
    total = np.zeros_like(wavelength)
    for centre, s_left, s_right, peak in components:
        sigma = np.where(wavelength < centre, s_left, s_right)
        total += peak * np.exp(-0.5 * ((wavelength - centre) / sigma) ** 2)
    return total


def model_eem(bands: BandGrid, excitation, emission) -> np.ndarray:
    """EEM [bands, bands] of a fluorophore with excitation spectrum a(λx) and emission density e(λm).

    EEM[i, j] = ⟨ a(λx) · ∫ r_j(λm) e(λm) H(λm − λx) dλm ⟩_{λx ∈ band i}: excitation averaged over
    band i's response, emission integrated over band j's, with the Stokes cut H (emission only at
    λm ≥ λx) applied wavelength by wavelength, then j < i zeroed. Kasha's rule: one emission
    shape for every excitation. Scaled to a maximum of 1. `excitation`, `emission`: numpy
    functions of wavelength [nm].
    """
    nodes, weights = bands.quadrature()
    widths = bands.effective_widths
    a = excitation(nodes) * weights  # [i, k]
    e = emission(nodes) * weights * widths[:, None]  # [j, l]
    allowed = nodes[None, None, :, :] >= nodes[:, :, None, None]  # [i, k, j, l]
    eem = np.einsum("ik,jl,ikjl->ij", a, e, allowed)
    eem = eem * stokes_mask(bands.num_bands)
    peak = eem.max()
    return eem / peak if peak > 0 else eem


def protoporphyrin_ix(bands: BandGrid = DEFAULT_BANDS, *, d=0.1, c=0.33, quantum_yield=0.1) -> Fluorophore:
    """Protoporphyrin IX: the tumour marker of PDD. Parametric band model (tissuefit/data/protoporphyrin_ix_model.csv).

    Absorption: Soret 405 nm (ε 1.65e5 /M/cm) and Q bands 505, 540, 575, 630 nm; emission peaks
    634 nm (σ 8 nm, 1.0) and 700 nm (σ 12 nm, 0.45). σ_f = ln(10) · ε · 10 µM (c = 1 ⇔ 10 µM).
    Defaults: d = 0.1, c = 0.33 (Zacher 2009 §3), φ = 0.1 (literature 0.06–0.16).
    """
    model = _band_model("protoporphyrin_ix_model.csv")
    ext = functools.partial(_gaussians, model["absorption"])
    emi = functools.partial(_gaussians, model["emission"])
    nodes, weights = bands.quadrature()
    sigma = LN10 * PPIX_REFERENCE_CONCENTRATION * np.sum(ext(nodes) * weights, axis=-1)
    return Fluorophore(
        name="protoporphyrin_ix", bands=bands, specific_absorption=sigma, eem=model_eem(bands, ext, emi),
        d=d, c=c, quantum_yield=quantum_yield,
    )


def collagen(bands: BandGrid = DEFAULT_BANDS, *, d=0.2, c=0.4, quantum_yield=0.1) -> Fluorophore:
    """Collagen: healthy mucosa's autofluorescence. Parametric model (tissuefit/data/collagen_model.csv).

    Excitation maximum 335 nm with a tail past 450 nm (asymmetric Gaussian, σ 25/50 nm), specific
    absorption 5 /cm at the maximum (d = c = 1; an order-of-magnitude assumption); emission a
    Gaussian at 490 nm, σ 45 nm. Defaults: d = 0.2, c = 0.4 (Zacher 2009 §3); φ = 0.1 is an
    assumption, not a measured value (only d·c·φ·σ_f is identifiable).
    """
    model = _band_model("collagen_model.csv")
    ext = functools.partial(_gaussians, model["absorption"])
    emi = functools.partial(_gaussians, model["emission"])
    nodes, weights = bands.quadrature()
    sigma = np.sum(ext(nodes) * weights, axis=-1)
    return Fluorophore(
        name="collagen", bands=bands, specific_absorption=sigma, eem=model_eem(bands, ext, emi),
        d=d, c=c, quantum_yield=quantum_yield,
    )


# ---------------------------------------------------------------------------------------------
# EEM files
# ---------------------------------------------------------------------------------------------


def read_eem(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read an EEM matrix file: excitation wavelengths [m], emission wavelengths [n], matrix [m, n].

    Format (CSV or whitespace separated, `#` comment lines allowed):

        excitation_nm\\emission_nm,400,416,...      <- header: a label, then emission wavelengths [nm]
        400,0.0,0.12,...                          <- one row per excitation wavelength [nm]

    Values are relative fluorescence intensities (photons per nm of emission), finite and ≥ 0.
    Raises ValueError naming the file, line and column for a ragged row (wrong shape), a
    non-number, NaN or inf, a negative value, or wavelengths that are not strictly increasing.
    """
    path = os.fspath(path)
    header, rows, _ = _parse_csv(path)
    if not header[0].lower().startswith("excitation"):
        raise ValueError(f"{path}: the header must start with a label such as 'excitation_nm\\emission_nm', got {header[0]!r}")
    if len(header) < 2 or not rows:
        raise ValueError(f"{path}: an EEM needs at least one emission wavelength and one excitation row")
    em = np.array([_parse_float(path, 1, "emission_nm header", t) for t in header[1:]])
    em = _check_increasing(f"{path}: emission_nm", em)
    ex = np.empty(len(rows))
    matrix = np.empty((len(rows), em.size))
    for r, (lineno, fields) in enumerate(rows):
        if len(fields) != em.size + 1:
            raise ValueError(
                f"{path} line {lineno}: expected {em.size + 1} values (excitation wavelength + {em.size} emission "
                f"values), got {len(fields)}; the matrix must be excitation rows × emission columns"
            )
        ex[r] = _parse_float(path, lineno, "excitation_nm", fields[0])
        for k, text in enumerate(fields[1:]):
            matrix[r, k] = _parse_float(path, lineno, f"emission {em[k]:g} nm", text)
            if matrix[r, k] < 0:
                raise ValueError(
                    f"{path} line {lineno}, column emission {em[k]:g} nm = {matrix[r, k]:g}: "
                    "EEM values are intensities, allowed [0, inf)"
                )
    ex = _check_increasing(f"{path}: excitation_nm", ex)
    return ex, em, matrix


def _checked_eem(excitation_nm, emission_nm, matrix, *, axis_prefix: str):
    """(excitation [nm], emission [nm], matrix) as float64 arrays, or ValueError naming what is wrong:
    axes strictly increasing, matrix excitation × emission, entries >= 0."""
    ex = _check_increasing(f"{axis_prefix}excitation_nm", excitation_nm)
    em = _check_increasing(f"{axis_prefix}emission_nm", emission_nm)
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (ex.size, em.size):
        raise ValueError(f"eem has shape {m.shape}; expected ({ex.size}, {em.size}) (excitation × emission)")
    check_range("eem", m, unit="-", low=0.0)
    return ex, em, m


def write_eem(path, excitation_nm, emission_nm, matrix, *, comment: str = "") -> None:
    """Write an EEM file that `read_eem` reads back exactly; `comment` becomes `#` lines (cite the source)."""
    ex, em, m = _checked_eem(excitation_nm, emission_nm, matrix, axis_prefix="")
    with atomic_writer(path) as fh:
        for line in comment.splitlines():
            fh.write(f"# {line}\n")
        fh.write(",".join(["excitation_nm\\emission_nm", *(repr(float(x)) for x in em)]) + "\n")
        for i in range(ex.size):
            fh.write(",".join(repr(float(x)) for x in [ex[i], *m[i]]) + "\n")


def eem_on_bands(bands: BandGrid, excitation_nm, emission_nm, matrix) -> np.ndarray:
    """Resample an EEM given at (excitation_nm, emission_nm) onto `bands` [bands, bands].

    If both axes are exactly the band centres the matrix is returned unchanged (a file written
    from a band EEM round-trips). Otherwise the matrix is interpolated bilinearly (zero outside
    its wavelength range: no data counts as no fluorescence), averaged over each excitation
    band's response and integrated over each emission band's response.
    """
    ex, em, m = _checked_eem(excitation_nm, emission_nm, matrix, axis_prefix="eem.")
    centres = bands.wavelengths
    def on_centres(x):
        return x.shape == centres.shape and np.allclose(x, centres, atol=1e-9, rtol=0)

    if on_centres(ex) and on_centres(em):
        return m.copy()
    if ex.size < 2 or em.size < 2:
        raise ValueError("eem: resampling onto a band grid needs at least two excitation and two emission wavelengths")
    from scipy.interpolate import RegularGridInterpolator

    interp = RegularGridInterpolator((ex, em), m, bounds_error=False, fill_value=0.0)
    nodes, weights = bands.quadrature()
    flat = nodes.reshape(-1)
    grid = interp(np.stack(np.meshgrid(flat, flat, indexing="ij"), axis=-1))  # [i*k, j*l]
    nb, k = nodes.shape
    grid = grid.reshape(nb, k, nb, k)
    out = np.einsum("ik,jl,ikjl->ij", weights, weights * bands.effective_widths[:, None], grid)
    return out

