"""Per-layer, per-band optical properties from spectral models: absorbers, scattering, overrides.

A layer's optics is a `LayerOptics`: a tuple of absorbers (their `mua` add up), one scatterer
(`mus`, `g`) and optional per-band overrides. `LayerOptics.properties(bands)` returns the arrays
`mua`, `mus`, `g` [bands] the transport consumes. Every model coefficient is a float array field
(a traced leaf), and every method is a plain JAX function of those leaves, so `jax.grad` flows
from the per-band properties to blood fraction, saturation, vessel radius, scattering amplitude
and power, concentrations and so on. The band grid is static and passed in.

Models (docs/design.md §3, SOURCES.md "Tissue optics, 400–720 nm"):
- `Blood`: oxy- and deoxy-hemoglobin from Prahl's table (tissuefit/data/hemoglobin_prahl.csv),
  with volume fraction, saturation and optional vessel packaging (Svaasand et al. 1995;
  van Veen et al. 2002).
- `TabulatedAbsorber`: any chromophore from a user's extinction table (cm⁻¹/M) and a molar
  concentration.
- `ConstantAbsorption`: a fixed mua [1/cm], the same in every band or one value per band.
- `PowerLawScattering`: mus'(λ) = a (λ/500 nm)^(−b) (Jacques 2013), mus = mus'/(1 − g).
- `ConstantScattering`: fixed mus, g.
- `BandOverride`: replace mua / mus / g in named bands by given values.

Nonlinear models (vessel packaging) are evaluated at each quadrature node and then band-averaged,
so the band value is the mean of the packaged coefficient over the band, not the packaging of the
mean. Linear models are simply band averages.
"""

from __future__ import annotations

import abc
import functools
import importlib.resources
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._checks import check_range, f64
from ._spectra import BandGrid, _check_increasing, _pick_column, read_spectrum_table

LN10 = math.log(10.0)
HEMOGLOBIN_G_PER_L = 150.0
"""Hemoglobin concentration of whole blood [g/L] (Prahl's conversion)."""
HEMOGLOBIN_G_PER_MOL = 64500.0
"""Gram molecular weight of hemoglobin [g/mol] (Prahl's conversion)."""


def _data_path(name: str):
    return importlib.resources.files("tissuefit").joinpath("data", name)


@functools.lru_cache(maxsize=1)
def hemoglobin_table() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Prahl's molar extinction of hemoglobin: wavelengths [nm], HbO2 and Hb [cm⁻¹/M] (2 nm steps).

    Measured data compiled by S. Prahl from Gratzer and Kollias; provenance in
    tissuefit/data/SOURCES.md. Read-only numpy arrays.
    """
    with importlib.resources.as_file(_data_path("hemoglobin_prahl.csv")) as path:
        wl, cols = read_spectrum_table(path)
    out = (wl, cols["hbo2"], cols["hb"])
    for arr in out:
        arr.setflags(write=False)
    return out


def hemoglobin_extinction(bands: BandGrid) -> tuple[Float[Array, " bands"], Float[Array, " bands"]]:
    """Band-averaged molar extinction of HbO2 and Hb [cm⁻¹/M] on `bands` (linear interpolation of the 2 nm table)."""
    wl, hbo2, hb = hemoglobin_table()
    weights = jnp.asarray(bands.table_weights(wl, field="hemoglobin table"))
    return weights @ jnp.asarray(hbo2), weights @ jnp.asarray(hb)


def packaging_factor(mua_blood, vessel_radius):
    """Vessel packaging factor C = (1 − exp(−2 mua_bl R)) / (2 mua_bl R) [-], in (0, 1].

    Svaasand et al. 1995 (Lasers Med Sci 10:235); van Veen et al. 2002 (Opt Lett 27:246):
    blood confined to vessels of radius R [cm] absorbs less than the same blood spread evenly,
    because the vessel cores are shadowed. `mua_blood` [1/cm] is the absorption of whole blood.
    C → 1 as R → 0 (evaluated with a series below x = 2 mua_bl R = 1e-4, so value and gradient
    are exact and finite at R = 0). Differentiable in both arguments.
    """
    x = 2.0 * mua_blood * vessel_radius
    small = x < 1e-4
    x_safe = jnp.where(small, 1.0, x)
    exact = -jnp.expm1(-x_safe) / x_safe
    series = 1.0 - x / 2.0 + x * x / 6.0
    return jnp.where(small, series, exact)


# ---------------------------------------------------------------------------------------------
# Absorbers
# ---------------------------------------------------------------------------------------------


class AbstractAbsorber(eqx.Module):
    """Something that absorbs: `absorption(bands)` gives its mua [1/cm] per band."""

    @abc.abstractmethod
    def absorption(self, bands: BandGrid) -> Float[Array, " bands"]:
        """Absorption coefficient mua [1/cm] per band, a differentiable function of the fields."""


def _per_band(field: str, value: Array, bands: BandGrid) -> Array:
    """Broadcast a scalar to [bands], or check that a 1-D value has one entry per band."""
    if value.ndim == 0:
        return jnp.broadcast_to(value, (bands.num_bands,))
    if value.shape != (bands.num_bands,):
        raise ValueError(f"{field} has shape {value.shape}; expected a scalar or one value per band ({bands.num_bands})")
    return value


class ConstantAbsorption(AbstractAbsorber):
    """A fixed absorption coefficient: `mua` [1/cm], ≥ 0; scalar (all bands) or [bands]. Differentiable."""

    mua: Float[Array, "*bands"] = eqx.field(converter=f64)

    def __check_init__(self):
        check_range("absorber.mua", self.mua, unit="1/cm", low=0.0)

    def absorption(self, bands):
        return _per_band("absorber.mua", self.mua, bands)


class Blood(AbstractAbsorber):
    """Whole blood at volume `fraction`, oxygen `saturation`, optionally packaged in vessels.

    Per wavelength (Prahl; SOURCES.md):

        mua_bl(λ) = ln(10) · [S ε_HbO2(λ) + (1 − S) ε_Hb(λ)] · hemoglobin / 64 500 g/mol
        mua(λ)    = fraction · C(λ) · mua_bl(λ),   C = (1 − exp(−2 mua_bl R)) / (2 mua_bl R)

    and the band value is the response-weighted mean of mua(λ) over the band (`BandGrid.average`;
    with `response="delta"` it is the value at the band centre: ln(10)·521 880·150/64 500 =
    2794.6 /cm at 416 nm for S = 1, fraction 1, R = 0, against 2570.5 /cm averaged over the
    default 408–424 nm band, the Soret peak being at 414 nm).

    Fields (all differentiable, likelihood-ratio unbiased downstream):
    - `fraction`: blood volume fraction [-], in [0, 1] (mucosa ~0.01–0.05).
    - `saturation`: oxygen saturation S [-], in [0, 1] (~0.6–0.8).
    - `vessel_radius`: R [cm], ≥ 0; 0 (default) = no packaging. Packaging matters at 400–440 nm.
    - `hemoglobin`: hemoglobin concentration of whole blood [g/L], > 0, default 150.
    """

    fraction: Float[Array, ""] = eqx.field(converter=f64)
    saturation: Float[Array, ""] = eqx.field(converter=f64)
    vessel_radius: Float[Array, ""] = eqx.field(default=0.0, converter=f64)
    hemoglobin: Float[Array, ""] = eqx.field(default=HEMOGLOBIN_G_PER_L, converter=f64)

    def __check_init__(self):
        check_range("blood.fraction", self.fraction, unit="-", low=0.0, high=1.0)
        check_range("blood.saturation", self.saturation, unit="-", low=0.0, high=1.0)
        check_range("blood.vessel_radius", self.vessel_radius, unit="cm", low=0.0)
        check_range("blood.hemoglobin", self.hemoglobin, unit="g/L", low=0.0, low_open=True)

    def whole_blood_mua(self, wavelength: Float[Array, "..."]) -> Float[Array, "..."]:
        """mua of whole blood [1/cm] at `wavelength` [nm] (no fraction, no packaging)."""
        wl, hbo2, hb = hemoglobin_table()
        x = jnp.asarray(wl)
        eps = self.saturation * jnp.interp(wavelength, x, jnp.asarray(hbo2)) + (1.0 - self.saturation) * jnp.interp(
            wavelength, x, jnp.asarray(hb)
        )
        return LN10 * eps * self.hemoglobin / HEMOGLOBIN_G_PER_MOL

    def absorption(self, bands):
        wl = hemoglobin_table()[0]
        bands.table_weights(wl, field="hemoglobin table")  # range check: ValueError outside 250–800 nm

        def mua(wavelength):
            mua_bl = self.whole_blood_mua(wavelength)
            return self.fraction * packaging_factor(mua_bl, self.vessel_radius) * mua_bl

        return bands.average(mua)


class TabulatedAbsorber(AbstractAbsorber):
    """A chromophore from a user-supplied molar extinction table: mua = ln(10) · ε(λ) · concentration.

    Fields:
    - `wavelengths`: static tuple [nm], strictly increasing; must cover the band grid.
    - `extinction`: decadic molar extinction ε [cm⁻¹/M], ≥ 0, one per wavelength (a leaf, normally frozen).
    - `concentration`: molar concentration [M], ≥ 0. Differentiable.
    The band value averages the linearly interpolated table over each band's response.
    """

    wavelengths: tuple[float, ...] = eqx.field(static=True)
    extinction: Float[Array, " n"]
    concentration: Float[Array, ""]

    def __init__(self, wavelengths, extinction, concentration):
        x = _check_increasing("absorber.wavelength_nm", wavelengths)
        eps = f64(extinction).reshape(-1)
        if eps.shape[0] != x.size:
            raise ValueError(f"absorber.extinction has {eps.shape[0]} entries but absorber.wavelength_nm has {x.size}")
        self.wavelengths = tuple(float(a) for a in x)
        self.extinction = eps
        self.concentration = f64(concentration)

    def __check_init__(self):
        check_range("absorber.extinction", self.extinction, unit="1/(cm M)", low=0.0)
        check_range("absorber.concentration", self.concentration, unit="M", low=0.0)

    @classmethod
    def from_file(cls, path, concentration, *, column: str | None = None) -> TabulatedAbsorber:
        """Read an extinction table (`wavelength_nm,<column>`, cm⁻¹/M; see `read_spectrum_table`)."""
        wl, cols = read_spectrum_table(path)
        return cls(wl, _pick_column(path, cols, column), concentration)

    def absorption(self, bands):
        eps = bands.average_table(self.wavelengths, self.extinction, field="absorber table")
        return LN10 * self.concentration * eps


# ---------------------------------------------------------------------------------------------
# Scatterers
# ---------------------------------------------------------------------------------------------


class AbstractScatterer(eqx.Module):
    """Something that scatters: `scattering(bands)` gives (mus [1/cm], g [-]) per band."""

    @abc.abstractmethod
    def scattering(self, bands: BandGrid) -> tuple[Float[Array, " bands"], Float[Array, " bands"]]:
        """Scattering coefficient mus [1/cm] and anisotropy g [-] per band."""


class PowerLawScattering(AbstractScatterer):
    """Reduced scattering as a power law: mus'(λ) = a (λ / 500 nm)^(−b); mus = mus' / (1 − g).

    Jacques 2013 (Phys Med Biol 58:R37); "other soft tissue": a = 18.9 /cm, b = 1.286.
    The band value of mus' is its mean over the band (for boxcar bands this differs from the
    centre value by a relative b(b+1)/24 · (width/λ)², 1e-4 at 500 nm); g is the same in every band.

    Fields (differentiable): `a` mus' at 500 nm [1/cm], ≥ 0; `b` scattering power [-], finite;
    `g` Henyey–Greenstein anisotropy [-], in (−1, 1) (tissue ~0.8–0.95).
    """

    a: Float[Array, ""] = eqx.field(converter=f64)
    b: Float[Array, ""] = eqx.field(converter=f64)
    g: Float[Array, ""] = eqx.field(converter=f64)

    REFERENCE_NM = 500.0

    def __check_init__(self):
        check_range("scattering.a", self.a, unit="1/cm", low=0.0)
        check_range("scattering.b", self.b, unit="-")
        check_range("scattering.g", self.g, unit="-", low=-1.0, high=1.0, low_open=True, high_open=True)

    def reduced_scattering(self, bands: BandGrid) -> Float[Array, " bands"]:
        """Band-averaged mus' [1/cm]."""
        return bands.average(lambda wl: self.a * (wl / self.REFERENCE_NM) ** (-self.b))

    def scattering(self, bands):
        mus = self.reduced_scattering(bands) / (1.0 - self.g)
        return mus, jnp.broadcast_to(self.g, mus.shape)


class ConstantScattering(AbstractScatterer):
    """Fixed `mus` [1/cm] ≥ 0 and `g` [-] in (−1, 1); scalars or [bands]. Differentiable."""

    mus: Float[Array, "*bands"] = eqx.field(converter=f64)
    g: Float[Array, "*bands"] = eqx.field(converter=f64)

    def __check_init__(self):
        check_range("scattering.mus", self.mus, unit="1/cm", low=0.0)
        check_range("scattering.g", self.g, unit="-", low=-1.0, high=1.0, low_open=True, high_open=True)

    def scattering(self, bands):
        return _per_band("scattering.mus", self.mus, bands), _per_band("scattering.g", self.g, bands)


# ---------------------------------------------------------------------------------------------
# A layer
# ---------------------------------------------------------------------------------------------


class BandOverride(eqx.Module):
    """Replace model values in chosen bands: after the models run, band `wavelengths[k]` gets
    `mua[k]`, `mus[k]`, `g[k]` for each quantity that is given (None = keep the model's).

    Fields: `wavelengths` static tuple of band centres [nm] (must be centres of the grid in use);
    `mua` [1/cm] ≥ 0, `mus` [1/cm] ≥ 0, `g` [-] in (−1, 1), each None or one value per listed
    band. Differentiable; the overridden bands carry no gradient to the underlying models.
    """

    wavelengths: tuple[float, ...] = eqx.field(static=True)
    mua: Float[Array, " k"] | None
    mus: Float[Array, " k"] | None
    g: Float[Array, " k"] | None

    def __init__(self, wavelengths, *, mua=None, mus=None, g=None):
        self.wavelengths = tuple(float(x) for x in np.asarray(wavelengths, dtype=np.float64).reshape(-1))
        k = len(self.wavelengths)
        for name, value in (("mua", mua), ("mus", mus), ("g", g)):
            if value is not None:
                value = f64(value).reshape(-1)
                if value.shape[0] != k:
                    raise ValueError(f"override.{name} has {value.shape[0]} values for {k} override wavelengths")
            setattr(self, name, value)

    def __check_init__(self):
        if self.mua is not None:
            check_range("override.mua", self.mua, unit="1/cm", low=0.0)
        if self.mus is not None:
            check_range("override.mus", self.mus, unit="1/cm", low=0.0)
        if self.g is not None:
            check_range("override.g", self.g, unit="-", low=-1.0, high=1.0, low_open=True, high_open=True)

    def apply(self, bands: BandGrid, mua, mus, g):
        idx = np.array([bands.index(w, field="override.wavelengths") for w in self.wavelengths], dtype=np.int32)
        if self.mua is not None:
            mua = mua.at[idx].set(self.mua)
        if self.mus is not None:
            mus = mus.at[idx].set(self.mus)
        if self.g is not None:
            g = g.at[idx].set(self.g)
        return mua, mus, g


class LayerOptics(eqx.Module):
    """One layer's optical properties as spectral models.

    Fields:
    - `absorbers`: tuple of `AbstractAbsorber` (blood, tabulated chromophores, constants,
      fluorophores); their mua add.
    - `scattering`: one `AbstractScatterer`.
    - `override`: optional `BandOverride`, applied last.
    Which absorbers exist is structure (changing it recompiles); their fields are parameters.
    """

    absorbers: tuple[AbstractAbsorber, ...]
    scattering: AbstractScatterer
    override: BandOverride | None = None

    def __init__(self, absorbers, scattering, override=None):
        absorbers = (absorbers,) if isinstance(absorbers, AbstractAbsorber) else tuple(absorbers)
        for k, a in enumerate(absorbers):
            if not isinstance(a, AbstractAbsorber):
                raise TypeError(f"layer.absorbers[{k}] is a {type(a).__name__}, not an absorber")
        if not isinstance(scattering, AbstractScatterer):
            raise TypeError(f"layer.scattering is a {type(scattering).__name__}, not a scatterer")
        if override is not None and not isinstance(override, BandOverride):
            raise TypeError(f"layer.override is a {type(override).__name__}, not a BandOverride")
        self.absorbers = absorbers
        self.scattering = scattering
        self.override = override

    def properties(self, bands: BandGrid) -> tuple[Float[Array, " bands"], Float[Array, " bands"], Float[Array, " bands"]]:
        """(mua [1/cm], mus [1/cm], g [-]) per band; differentiable in every model coefficient."""
        mua = jnp.zeros(bands.num_bands, jnp.result_type(float))  # float64 where enabled, no warning where not
        for a in self.absorbers:
            mua = mua + a.absorption(bands)
        mus, g = self.scattering.scattering(bands)
        if self.override is not None:
            mua, mus, g = self.override.apply(bands, mua, mus, g)
        return mua, mus, g


def stack_layers(layers, bands: BandGrid) -> tuple[Array, Array, Array]:
    """`properties` of each layer stacked: (mua, mus, g), each [layers, bands]."""
    props = [layer.properties(bands) for layer in layers]
    if not props:
        raise ValueError("layers: at least one layer is required")
    return tuple(jnp.stack([p[k] for p in props]) for k in range(3))  # type: ignore[return-value]

