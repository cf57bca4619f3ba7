"""Multi-spectral tissue and scenes: layers described by spectral models, lesion regions, a source spectrum.

`SpectralTissue` is the multi-band counterpart of `LayeredTissue`: the geometry (refractive index
and thickness per layer, ambient indices) is the same, and each layer's optics is a `LayerOptics`
(absorbers, fluorophores, scattering, overrides) evaluated on a static `BandGrid`. Lesions are
regions (`Sphere`, `Box`) inside a layer with their own `LayerOptics`.

The tracer sees *media*: the layers first (index l), then each region's (one for a sphere or a
box, one per voxel for a `VoxelGrid`; `region_offsets`). `properties` gives mua, mus, g per
medium and band, `conversion` the fluorescence conversion matrices per medium
(docs/design.md §6; the model is in `Fluorophore`).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._checks import is_concrete
from ._fluorophores import Fluorophore, Quantity, layer_conversion
from ._optics import LayerOptics
from ._regions import AbstractRegion, check_regions
from ._source import AbstractSource, PencilBeam
from ._spectra import DEFAULT_BANDS, AbstractSpectrum, BandGrid, FlatSpectrum
from ._tissue import LayeredTissue


class SpectralTissue(eqx.Module):
    """Plane-parallel layers below z = 0 with per-band optics from spectral models.

    Fields:
    - `bands`: static `BandGrid` (default: 400–720 nm, 16 nm boxcars, 21 bands).
    - `layers`: tuple of `LayerOptics`, top first. Their coefficients are differentiable.
    - `n`, `thickness`, `n_above`, `n_below`: as in `LayeredTissue` (n is the same in every band;
      not differentiable). The last layer may be semi-infinite.
    - `regions`: tuple of lesion regions (`Sphere`, `Box`), default none.
    - `quantity`: static, "photons" (default: weights count photons; emission carries the quantum
      yield) or "energy" (weights are radiant power; emission also carries λ_ex/λ_em).
    """

    bands: BandGrid = eqx.field(static=True)
    layers: tuple[LayerOptics, ...]
    geometry: LayeredTissue
    regions: tuple[AbstractRegion, ...]
    quantity: Quantity = eqx.field(static=True)

    def __init__(self, layers, *, n, thickness, n_above=1.0, n_below=1.0, bands: BandGrid = DEFAULT_BANDS,
                 regions=(), quantity: Quantity = "photons"):
        layers = (layers,) if isinstance(layers, LayerOptics) else tuple(layers)
        for k, layer in enumerate(layers):
            if not isinstance(layer, LayerOptics):
                raise TypeError(f"layers[{k}] is a {type(layer).__name__}, not a LayerOptics")
        if not isinstance(bands, BandGrid):
            raise TypeError(f"bands is a {type(bands).__name__}, not a BandGrid")
        if quantity not in ("photons", "energy"):
            raise ValueError(f"quantity = {quantity!r}; allowed 'photons' or 'energy'")
        count = len(layers)
        # Geometry is checked by LayeredTissue; its optical fields are placeholders (never traced).
        ones = np.ones(count)
        self.geometry = LayeredTissue(n=n, mua=ones, mus=ones, g=0.0 * ones, thickness=thickness,
                                      n_above=n_above, n_below=n_below)
        if self.geometry.num_layers != count:
            raise ValueError(
                f"layers: {count} LayerOptics but n and thickness describe {self.geometry.num_layers} layers"
            )
        regions = (regions,) if isinstance(regions, AbstractRegion) else tuple(regions)
        check_regions(regions, count)
        self.layers = layers
        self.regions = regions
        self.bands = bands
        self.quantity = quantity

    @property
    def num_layers(self) -> int:
        return len(self.layers)

    @property
    def num_media(self) -> int:
        return len(self.layers) + sum(r.num_media for r in self.regions)

    def region_offsets(self) -> tuple[int, ...]:
        """Medium index of each region's first medium (static): layers first, then the regions'."""
        offsets, start = [], len(self.layers)
        for r in self.regions:
            offsets.append(start)
            start += r.num_media
        return tuple(offsets)

    def properties(self) -> tuple[Float[Array, "media bands"], Float[Array, "media bands"], Float[Array, "media bands"]]:
        """(mua [1/cm], mus [1/cm], g [-]) per medium and band. Differentiable in every coefficient."""
        layers = [layer.properties(self.bands) for layer in self.layers]
        regions = [r.properties(self.bands) for r in self.regions]
        return tuple(  # type: ignore[return-value]
            jnp.concatenate([jnp.stack([p[k] for p in layers])] + [r[k] for r in regions]) for k in range(3)
        )

    def conversion(self) -> Float[Array, "media bands bands"]:
        """P[m, i, j]: weight moved from band i to band j per unit weight at an interaction in medium m,
        summed over the medium's fluorophores (`Fluorophore`; `layer_conversion`)."""
        layers = jnp.stack([layer_conversion(m, self.bands, quantity=self.quantity).sum(0) for m in self.layers])
        return jnp.concatenate([layers] + [r.conversion(self.bands, self.quantity) for r in self.regions])

    def medium_at(self, points: Float[Array, "n 3"]) -> Array:
        """Medium index (as `properties()` orders media) of points [n, 3] (x, y, depth z >= 0) [cm]:
        the region medium containing them (a voxel grid's voxel), else their layer. Points on a face
        belong to the layer below it; points below the last layer to the last layer."""
        p = jnp.asarray(points)
        z0 = self.geometry.z0.astype(p.dtype)
        layer = jnp.clip(jnp.searchsorted(z0, p[:, 2], side="right") - 1, 0, self.num_layers - 1).astype(jnp.int32)
        return self.medium_in_layer(layer, p.T)

    def medium_in_layer(self, layer: Array, p: Float[Array, "3 n"]) -> Array:
        """Medium index of points `p` [3, n] (x, y, depth) [cm] known to lie in layer `layer` [n]:
        the region medium of that layer containing them, else the layer."""
        medium = layer
        for region, offset in zip(self.regions, self.region_offsets()):
            inside = (layer == region.layer) & region.contains(p)
            medium = jnp.where(inside, offset + region.local_medium(p), medium)
        return medium

    @property
    def fluorescent(self) -> bool:
        """Whether any medium holds a fluorophore (static: decides whether conversion code exists)."""
        optics = self.layers + tuple(r.optics for r in self.regions)
        return any(isinstance(a, Fluorophore) for m in optics for a in m.absorbers)

    def at_band(self, band: int) -> LayeredTissue:
        """The single-band `LayeredTissue` of band index `band` (regions ignored; for comparisons)."""
        if self.regions:
            raise ValueError("at_band: a tissue with regions has no single-band LayeredTissue equivalent")
        mua, mus, g = self.properties()
        geo = self.geometry
        return LayeredTissue(n=geo.n, mua=mua[: self.num_layers, band], mus=mus[: self.num_layers, band],
                             g=g[: self.num_layers, band], thickness=geo.thickness, n_above=geo.n_above,
                             n_below=geo.n_below)


class SpectralScene(eqx.Module):
    """A multi-spectral scene: `tissue` (SpectralTissue), `source` (geometry of the launch, default a
    normal pencil beam) and `spectrum` (the source's spectral power density, default flat white).

    The band powers the tracer launches are `spectrum.band_power(tissue.bands)` (summing to 1).
    """

    tissue: SpectralTissue
    source: AbstractSource = eqx.field(default_factory=PencilBeam)
    spectrum: AbstractSpectrum = eqx.field(default_factory=FlatSpectrum)

    def __check_init__(self):
        if not isinstance(self.tissue, SpectralTissue):
            raise TypeError(f"scene.tissue is a {type(self.tissue).__name__}, not a SpectralTissue")
        if not isinstance(self.source, AbstractSource):
            raise TypeError(f"scene.source is a {type(self.source).__name__}, not a source (AbstractSource)")
        if not isinstance(self.spectrum, AbstractSpectrum):
            raise TypeError(f"scene.spectrum is a {type(self.spectrum).__name__}, not a spectrum (AbstractSpectrum)")

    def band_power(self) -> Float[Array, " bands"]:
        return self.spectrum.band_power(self.tissue.bands)

    def active_bands(self) -> tuple[int, ...]:
        """Bands that carry light: source power > 0, or reachable by emission from such a band.

        Decided in Python from concrete values (all bands when the spectrum or the EEMs are traced),
        so that bands nobody reads are not traced."""
        power = self.band_power()
        conv = self.tissue.conversion() if self.tissue.fluorescent else None
        nb = self.tissue.bands.num_bands
        if not is_concrete(power) or (conv is not None and not is_concrete(conv)):
            return tuple(range(nb))
        active = np.asarray(power) > 0
        if conv is not None:
            reach = np.asarray(conv).sum(0) > 0  # [i, j]: some medium converts i -> j
            for _ in range(nb):
                grown = active | reach[active].any(0)
                if np.array_equal(grown, active):
                    break
                active = grown
        return tuple(int(b) for b in np.nonzero(active)[0])
