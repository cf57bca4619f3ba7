"""Spectral bands and light-source spectra: how a continuous spectrum becomes one number per band.

A `BandGrid` is the camera's set of spectral bands (default 400–720 nm in 16 nm steps, 21 bands),
each with a response (default a 16 nm boxcar). Spectra are *integrated over each band's response*,
not sampled at the band centre: with 16 nm bands this matters wherever a spectrum changes on a
scale of a few nm (the hemoglobin and PpIX Soret bands are ~20 nm wide).

Two reductions, both linear in the spectrum and therefore differentiable in anything it depends on:
- `BandGrid.average(f)`: the response-weighted mean of f over band b, ∫ r_b f dλ / ∫ r_b dλ. Use it
  for coefficients (mua, mus, extinction): a band's coefficient is the mean over the band.
- `BandGrid.integrate(f)`: ∫ r_b f dλ with the response's peak equal to 1; = average × effective
  width. Use it for spectral densities (a source in W/nm, an emission spectrum in photons/nm) to
  get the power (photons) falling in the band.

The integrals are quadratures on a fine sub-grid fixed by the static grid (midpoint rule, `step`
nm per node). The midpoint rule is exact for a spectrum that is linear on each sub-interval, so a
constant or linear spectrum comes out exact, and a table tabulated on multiples of `step` whose
breakpoints fall on sub-interval edges (Prahl's 2 nm table on the default grid) is integrated
exactly as its piecewise-linear interpolant.

This module also reads and writes the plain-text spectrum tables users supply (CSV, `#` comments,
a header row whose first column is `wavelength_nm`).
"""

from __future__ import annotations

import abc
import functools
import math
import os
from collections.abc import Callable, Mapping, Sequence
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._atomic import atomic_writer
from .._checks import check_range, f64, is_concrete

Response = Literal["boxcar", "gaussian", "delta"]
_RESPONSES = ("boxcar", "gaussian", "delta")
_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))  # 2.3548...
_GAUSS_HALF_SUPPORT_SIGMAS = 5.0  # Gaussian responses are truncated at ±5 sigma (weight lost < 6e-7)


# ---------------------------------------------------------------------------------------------
# Band grid
# ---------------------------------------------------------------------------------------------


def _check_increasing(field: str, values, *, unit: str = "nm") -> np.ndarray:
    """Return `values` as float64 array, or raise unless finite and strictly increasing."""
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    check_range(field, arr, unit=unit)  # finite
    bad = np.nonzero(np.diff(arr) <= 0)[0]
    if bad.size:
        i = int(bad[0]) + 1
        raise ValueError(
            f"{field}[{i}] = {arr[i]:g} {unit} is not greater than {field}[{i - 1}] = {arr[i - 1]:g} {unit}; "
            "wavelengths must be strictly increasing"
        )
    return arr


@functools.lru_cache(maxsize=64)
def _quadrature(
    centers: tuple[float, ...], widths: tuple[float, ...], response: str, step: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nodes [bands, K] (nm), normalised weights [bands, K] and effective widths [bands] (nm)."""
    nodes, weights, eff = [], [], []
    for c, w in zip(centers, widths):
        if response == "delta":
            x, wt, e = np.array([c]), np.array([1.0]), w
        elif response == "boxcar":
            n = max(1, math.ceil(w / step - 1e-9))
            h = w / n
            x = c - w / 2 + (np.arange(n) + 0.5) * h
            wt, e = np.full(n, 1.0 / n), w
        else:  # gaussian, FWHM = w; symmetric midpoint nodes, exact for linear spectra
            sigma = w / _FWHM_PER_SIGMA
            half = _GAUSS_HALF_SUPPORT_SIGMAS * sigma
            n = max(2, math.ceil(2 * half / step))
            h = 2 * half / n
            x = c - half + (np.arange(n) + 0.5) * h
            r = np.exp(-0.5 * ((x - c) / sigma) ** 2)
            wt, e = r / r.sum(), sigma * math.sqrt(2 * math.pi)
        nodes.append(x)
        weights.append(wt)
        eff.append(e)
    k = max(len(x) for x in nodes)
    node_arr = np.array([np.pad(x, (0, k - len(x)), constant_values=x[len(x) // 2]) for x in nodes])
    weight_arr = np.array([np.pad(wt, (0, k - len(wt))) for wt in weights])
    for arr in (node_arr, weight_arr):
        arr.setflags(write=False)
    return node_arr, weight_arr, np.array(eff)


class BandGrid(eqx.Module):
    """The spectral bands a simulation carries: centres, widths and response shape. Static.

    Every field is static (plain Python, hashable): changing the grid changes array shapes and
    recompiles, changing any parameter does not. Nothing here is differentiable.

    Arguments / fields:
    - `centers`: band centres [nm], strictly increasing. Default 400, 416, …, 720 (21 bands).
    - `widths`: band widths [nm], > 0; one number for all bands or one per band. For "boxcar" the
      full width, for "gaussian" the FWHM, for "delta" only the nominal width used by
      `integrate`. Default: the spacing of the centres (16 nm on the default grid), so boxcars
      tile the spectrum without gaps or overlaps.
    - `response`: "boxcar" (flat over [centre − width/2, centre + width/2], the default),
      "gaussian" (FWHM = width, truncated at ±5 σ) or "delta" (sample at the centre: the
      un-integrated approximation, for comparison).
    - `step`: quadrature step [nm], > 0, default 0.5.

    Use `BandGrid.uniform(start, stop, spacing)` for evenly spaced bands.
    """

    centers: tuple[float, ...] = eqx.field(static=True)
    widths: tuple[float, ...] = eqx.field(static=True)
    response: Response = eqx.field(static=True)
    step: float = eqx.field(static=True)

    def __init__(self, centers=None, widths=None, *, response: Response = "boxcar", step: float = 0.5):
        if centers is None:
            centers = np.arange(400.0, 720.0 + 1e-9, 16.0)
        c = _check_increasing("bands.centers", centers)
        if c.size < 1:
            raise ValueError("bands.centers: at least one band is required")
        check_range("bands.centers", c, unit="nm", low=0.0, low_open=True)
        if widths is None:
            if c.size == 1:
                w = np.array([16.0])
            else:
                edges = np.concatenate([[c[0] - (c[1] - c[0]) / 2], (c[1:] + c[:-1]) / 2, [c[-1] + (c[-1] - c[-2]) / 2]])
                w = np.diff(edges)
        else:
            w = np.asarray(widths, dtype=np.float64).reshape(-1)
            if w.size == 1:
                w = np.full(c.size, float(w[0]))
            if w.size != c.size:
                raise ValueError(
                    f"bands.widths has {w.size} entries but bands.centers has {c.size}; give one width or one per band"
                )
        check_range("bands.widths", w, unit="nm", low=0.0, low_open=True)
        if response not in _RESPONSES:
            raise ValueError(f"bands.response = {response!r} is not one of {', '.join(map(repr, _RESPONSES))}")
        check_range("bands.step", step, unit="nm", low=0.0, low_open=True)
        self.centers = tuple(float(x) for x in c)
        self.widths = tuple(float(x) for x in w)
        self.response = response
        self.step = float(step)

    @classmethod
    def uniform(
        cls,
        start: float = 400.0,
        stop: float = 720.0,
        spacing: float = 16.0,
        *,
        width: float | None = None,
        response: Response = "boxcar",
        step: float = 0.5,
    ) -> BandGrid:
        """Bands centred at start, start + spacing, …, stop [nm]; width defaults to the spacing."""
        check_range("bands.spacing", spacing, unit="nm", low=0.0, low_open=True)
        check_range("bands.stop", stop, unit="nm", low=float(start))
        n = int(math.floor((stop - start) / spacing + 1e-9)) + 1
        centers = start + spacing * np.arange(n)
        return cls(centers, spacing if width is None else width, response=response, step=step)

    # -- shape and lookup ---------------------------------------------------------------------

    @property
    def num_bands(self) -> int:
        return len(self.centers)

    @property
    def wavelengths(self) -> np.ndarray:
        """Band centres [nm] as a float64 numpy array [bands]."""
        return np.asarray(self.centers, dtype=np.float64)

    @property
    def effective_widths(self) -> np.ndarray:
        """∫ r_b dλ [nm] for each band's peak-normalised response [bands]."""
        return _quadrature(self.centers, self.widths, self.response, self.step)[2]

    def index(self, wavelength_nm: float, *, field: str = "wavelength") -> int:
        """Index of the band centred at `wavelength_nm` (within 1e-6 nm); ValueError otherwise."""
        hits = np.nonzero(np.abs(self.wavelengths - float(wavelength_nm)) < 1e-6)[0]
        if hits.size != 1:
            raise ValueError(
                f"{field} = {float(wavelength_nm):g} nm is not a band centre; allowed "
                f"{', '.join(f'{x:g}' for x in self.centers)} nm"
            )
        return int(hits[0])

    def quadrature(self) -> tuple[np.ndarray, np.ndarray]:
        """Nodes [bands, K] in nm and weights [bands, K] summing to 1 per band (numpy, static).

        Padded entries have weight 0. `average(f) = sum(weights * f(nodes), -1)`.
        """
        nodes, weights, _ = _quadrature(self.centers, self.widths, self.response, self.step)
        return nodes, weights

    # -- reductions ---------------------------------------------------------------------------

    def average(self, spectrum: Callable[[Array], Array]) -> Float[Array, "... bands"]:
        """Response-weighted band mean of `spectrum` (a JAX function of wavelength in nm).

        `spectrum` receives an array [bands, K] of wavelengths [nm] and returns [..., bands, K];
        the result is [..., bands] in the spectrum's own unit. Differentiable in whatever the
        spectrum closes over (pass parameters through the Module that owns them).
        """
        nodes, weights = self.quadrature()
        values = spectrum(jnp.asarray(nodes))
        return jnp.sum(values * jnp.asarray(weights), axis=-1)

    def integrate(self, spectrum: Callable[[Array], Array]) -> Float[Array, "... bands"]:
        """∫ r_b(λ) spectrum(λ) dλ per band, response peak 1: average × effective width.

        A spectral density in X/nm gives X per band (e.g. W/nm → W). For boxcar bands that tile
        the axis, the sum over bands is the integral of the spectrum over the grid's span.
        """
        return self.average(spectrum) * jnp.asarray(self.effective_widths)

    def table_weights(self, wavelengths, *, field: str = "table") -> np.ndarray:
        """Matrix W [bands, n] with band averages = W @ values for a table sampled at `wavelengths`.

        The table is read as its piecewise-linear interpolant. Raises ValueError if the table's
        wavelengths are not strictly increasing or do not cover every quadrature node of the grid.
        """
        x = _check_increasing(f"{field}.wavelength_nm", wavelengths)
        nodes, weights = self.quadrature()
        used = nodes[weights > 0]
        lo, hi = float(used.min()), float(used.max())
        if x.size < 2 or x[0] > lo + 1e-9 or x[-1] < hi - 1e-9:
            raise ValueError(
                f"{field} covers {x[0]:g}–{x[-1]:g} nm but the band grid needs {lo:g}–{hi:g} nm; "
                "extend the table to cover every band's response"
            )
        flat = np.clip(nodes.reshape(-1), x[0], x[-1])
        j = np.clip(np.searchsorted(x, flat, side="right") - 1, 0, x.size - 2)
        t = (flat - x[j]) / (x[j + 1] - x[j])
        interp = np.zeros((flat.size, x.size))
        rows = np.arange(flat.size)
        interp[rows, j] += 1.0 - t
        interp[rows, j + 1] += t
        interp = interp.reshape(nodes.shape + (x.size,))
        return np.einsum("bk,bkn->bn", weights, interp)

    def average_table(self, wavelengths, values, *, field: str = "table") -> Float[Array, "... bands"]:
        """Band averages of a tabulated spectrum: `values` [..., n] sampled at `wavelengths` [n] (nm).

        Linear in `values`, so differentiable in them; `wavelengths` are static.
        """
        w = jnp.asarray(self.table_weights(wavelengths, field=field))
        v = jnp.asarray(values, dtype=jnp.float64)
        if v.shape[-1] != w.shape[1]:
            raise ValueError(f"{field}: {v.shape[-1]} values for {w.shape[1]} wavelengths")
        return v @ w.T


DEFAULT_BANDS = BandGrid()
"""The paper's camera: 400–720 nm, 16 nm boxcar bands (21 bands)."""


# ---------------------------------------------------------------------------------------------
# Source spectra
# ---------------------------------------------------------------------------------------------


class AbstractSpectrum(eqx.Module):
    """A source's relative spectral power density S(λ) [1/nm, arbitrary scale]."""

    @abc.abstractmethod
    def __call__(self, wavelength: Float[Array, "..."]) -> Float[Array, "..."]:
        """S at `wavelength` [nm]."""

    def band_power(self, bands: BandGrid, *, normalize: bool = True) -> Float[Array, " bands"]:
        """Power per band, ∫ r_b S dλ [S × nm]; with `normalize` (default) scaled to sum to 1.

        Normalised, it is the fraction of the source's in-grid power that each band receives:
        the per-band weight a launched photon packet carries. Differentiable in the spectrum's
        parameters.
        """
        p = bands.integrate(self)
        if normalize:
            p = p / jnp.sum(p)
        return p


class FlatSpectrum(AbstractSpectrum):
    """White light with a flat spectral power density (1 per nm). No parameters."""

    def __call__(self, wavelength):
        return jnp.ones_like(jnp.asarray(wavelength, dtype=jnp.float64))


class LongpassFilter(AbstractSpectrum):
    """A long-pass transmission curve with a smooth (logistic) edge, for camera observation filters:

        T(λ) = blocked + (passed − blocked) / (1 + exp(−(λ − cut) / width))

    Fields [nm, -]: `cut_nm`, `width_nm` (> 0, the edge's logistic scale), `blocked` and `passed`
    (transmission below and above the edge, in [0, 1]), all differentiable. PDD cameras observe
    through such a filter: it blocks most of the violet excitation remitted by the tissue (leaving a
    little for orientation) and passes the red PpIX fluorescence. Product curves differ; measure
    yours and pass a `TabulatedSpectrum` for quantitative work.
    """

    cut_nm: Float[Array, ""] = eqx.field(converter=f64)
    width_nm: Float[Array, ""] = eqx.field(default=5.0, converter=f64)
    blocked: Float[Array, ""] = eqx.field(default=0.0, converter=f64)
    passed: Float[Array, ""] = eqx.field(default=1.0, converter=f64)

    def __check_init__(self):
        check_range("filter.cut_nm", self.cut_nm, unit="nm", low=0.0, low_open=True)
        check_range("filter.width_nm", self.width_nm, unit="nm", low=0.0, low_open=True)
        check_range("filter.blocked", self.blocked, unit="-", low=0.0, high=1.0)
        check_range("filter.passed", self.passed, unit="-", low=0.0, high=1.0)

    def __call__(self, wavelength):
        return self.blocked + (self.passed - self.blocked) * jax.nn.sigmoid((wavelength - self.cut_nm) / self.width_nm)


class GaussianSpectrum(AbstractSpectrum):
    """A Gaussian emission line, peak 1: S(λ) = exp(−4 ln2 (λ − center)² / fwhm²).

    Fields: `center_nm` [nm] and `fwhm_nm` [nm, > 0], both differentiable. An LED is well
    described by this shape; see `violet_led`.
    """

    center_nm: Float[Array, ""] = eqx.field(converter=f64)
    fwhm_nm: Float[Array, ""] = eqx.field(converter=f64)

    def __check_init__(self):
        check_range("spectrum.center_nm", self.center_nm, unit="nm", low=0.0, low_open=True)
        check_range("spectrum.fwhm_nm", self.fwhm_nm, unit="nm", low=0.0, low_open=True)

    def __call__(self, wavelength):
        sigma = self.fwhm_nm / _FWHM_PER_SIGMA
        return jnp.exp(-0.5 * ((wavelength - self.center_nm) / sigma) ** 2)


class BoxcarSpectrum(AbstractSpectrum):
    """A flat band between `low_nm` and `high_nm` [nm] (1 inside, 0 outside): a filtered lamp.

    The edges are fields (arrays) but the spectrum is a step function of them: their gradient is
    zero almost everywhere. Use `GaussianSpectrum` when edges are to be fitted.
    """

    low_nm: Float[Array, ""] = eqx.field(converter=f64)
    high_nm: Float[Array, ""] = eqx.field(converter=f64)

    def __check_init__(self):
        check_range("spectrum.low_nm", self.low_nm, unit="nm", low=0.0, low_open=True)
        if is_concrete(self.low_nm):
            check_range("spectrum.high_nm", self.high_nm, unit="nm", low=float(np.asarray(self.low_nm)), low_open=True)

    def __call__(self, wavelength):
        w = jnp.asarray(wavelength, dtype=jnp.float64)
        return jnp.where((w >= self.low_nm) & (w < self.high_nm), 1.0, 0.0)


class TabulatedSpectrum(AbstractSpectrum):
    """A measured spectrum: `values` [n] (≥ 0, differentiable) at static `wavelengths` [n] (nm).

    Linear interpolation between samples, zero outside the table (no light there).
    """

    wavelengths: tuple[float, ...] = eqx.field(static=True)
    values: Float[Array, " n"]

    def __init__(self, wavelengths, values):
        x = _check_increasing("spectrum.wavelength_nm", wavelengths)
        v = f64(values).reshape(-1)
        if v.shape[0] != x.size:
            raise ValueError(f"spectrum.values has {v.shape[0]} entries but spectrum.wavelength_nm has {x.size}")
        check_range("spectrum.values", v, unit="-", low=0.0)
        self.wavelengths = tuple(float(a) for a in x)
        self.values = v

    @classmethod
    def from_file(cls, path, column: str | None = None) -> TabulatedSpectrum:
        """Read a spectrum table (see `read_spectrum_table`); `column` defaults to the only one."""
        wl, cols = read_spectrum_table(path)
        return cls(wl, _pick_column(path, cols, column))

    def __call__(self, wavelength):
        x = jnp.asarray(self.wavelengths)
        return jnp.interp(jnp.asarray(wavelength, dtype=jnp.float64), x, self.values, left=0.0, right=0.0)


def violet_led(center_nm: float = 405.0, fwhm_nm: float = 15.0) -> GaussianSpectrum:
    """The violet excitation source of PDD: a 405 nm LED, Gaussian, FWHM 15 nm by default.

    405 nm sits on the PpIX Soret maximum. Typical violet LEDs have a FWHM of 10–20 nm; 15 nm is
    our default, not a specific product's datum (measure and pass a `TabulatedSpectrum` for a
    real light source). Filtered-lamp PDD systems are closer to a `BoxcarSpectrum` over roughly
    380–440 nm.
    """
    return GaussianSpectrum(center_nm=center_nm, fwhm_nm=fwhm_nm)


# ---------------------------------------------------------------------------------------------
# Plain-text tables
# ---------------------------------------------------------------------------------------------


def _parse_csv(path) -> tuple[list[str], list[tuple[int, list[str]]], list[str]]:
    """Header fields, data rows (line number, fields) and comment lines of a `#`-commented CSV."""
    path = os.fspath(path)
    header, rows, comments = None, [], []
    with open(path, encoding="utf-8") as fh:
        for lineno, line in enumerate(fh, start=1):
            text = line.strip()
            if not text:
                continue
            if text.startswith("#"):
                comments.append(text[1:].strip())
                continue
            fields = [f.strip() for f in (text.split(",") if "," in text else text.split())]
            if header is None:
                header = fields
            else:
                rows.append((lineno, fields))
    if header is None:
        raise ValueError(f"{path}: no header row found")
    return header, rows, comments


def _parse_float(path, lineno: int, column: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{path} line {lineno}, column {column}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"{path} line {lineno}, column {column} = {text}: values must be finite numbers")
    return value


def read_spectrum_table(path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read a spectrum table: `#` comment lines, a header `wavelength_nm,<name>,…`, numeric rows.

    Returns the wavelengths [n] (nm, strictly increasing) and a dict name → values [n].
    Raises ValueError naming the file, line and column for a missing/ragged entry, a non-number,
    NaN or inf, or wavelengths that do not increase.
    """
    path = os.fspath(path)
    header, rows, _ = _parse_csv(path)
    if header[0].lower() != "wavelength_nm" or len(header) < 2:
        raise ValueError(f"{path}: header must be 'wavelength_nm,<column>,...'; got {','.join(header)!r}")
    if len(rows) < 2:
        raise ValueError(f"{path}: at least two rows of data are required, got {len(rows)}")
    data = np.empty((len(rows), len(header)))
    for r, (lineno, fields) in enumerate(rows):
        if len(fields) != len(header):
            raise ValueError(f"{path} line {lineno}: expected {len(header)} values ({','.join(header)}), got {len(fields)}")
        for k, text in enumerate(fields):
            data[r, k] = _parse_float(path, lineno, header[k], text)
    wl = _check_increasing(f"{path}: wavelength_nm", data[:, 0])
    return wl, {name: data[:, k] for k, name in enumerate(header[1:], start=1)}


def write_spectrum_table(path, wavelengths, columns: Mapping[str, Sequence[float]], *, comment: str = "") -> None:
    """Write a table `read_spectrum_table` reads back exactly (repr precision); `comment` → `#` lines."""
    wl = _check_increasing("wavelength_nm", wavelengths)
    names = list(columns)
    values = [np.asarray(columns[n], dtype=np.float64).reshape(-1) for n in names]
    for name, v in zip(names, values):
        if v.size != wl.size:
            raise ValueError(f"column {name!r} has {v.size} values for {wl.size} wavelengths")
        check_range(name, v, unit="-")
    with atomic_writer(path) as fh:
        for line in comment.splitlines():
            fh.write(f"# {line}\n")
        fh.write(",".join(["wavelength_nm", *names]) + "\n")
        for i in range(wl.size):
            fh.write(",".join(repr(float(x)) for x in [wl[i], *(v[i] for v in values)]) + "\n")


def _pick_column(path, columns: Mapping[str, np.ndarray], column: str | None) -> np.ndarray:
    if column is None:
        if len(columns) != 1:
            raise ValueError(f"{os.fspath(path)} has columns {', '.join(columns)}; name the one to use")
        return next(iter(columns.values()))
    if column not in columns:
        raise ValueError(f"{os.fspath(path)} has no column {column!r}; columns: {', '.join(columns)}")
    return columns[column]
