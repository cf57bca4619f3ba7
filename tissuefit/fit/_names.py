"""Named fit parameters of a `SpectralTissue`, for the command line's `--free`:

    layer<i>.<field>   the i-th layer's optics       region<j>.<field>   the j-th region's optics

with fields `mua` (ConstantAbsorption; `mua1`, ... for a second one), `blood_fraction`,
`blood_saturation` (Blood), `c_<fluorophore>`, `yield_<fluorophore>` (Fluorophore; PpIX is also
`ppix`), `conc_<k>` (the k-th TabulatedAbsorber), `mus`, `g` (ConstantScattering), `a`, `b`, `g`
(PowerLawScattering). A bare field (`mua`, `c_ppix`) names the one medium that has it."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ..scene import Blood, ConstantAbsorption, ConstantScattering, Fluorophore, PowerLawScattering, TabulatedAbsorber
from ._parameters import FitParameter

SHORT_NAMES = {"protoporphyrin_ix": "ppix"}


def _optics_fields(optics, get):
    """[(field, where, transform, units[, bounds])] of one LayerOptics; `get(tissue)` returns the optics."""
    out = []
    n_const = n_tab = 0
    for i, ab in enumerate(optics.absorbers):
        def at(t, i=i):
            return get(t).absorbers[i]

        if isinstance(ab, ConstantAbsorption):
            name = "mua" if n_const == 0 else f"mua{n_const}"
            n_const += 1
            out.append((name, lambda t, at=at: at(t).mua, "log", "1/cm"))
        elif isinstance(ab, Blood):
            out.append(("blood_fraction", lambda t, at=at: at(t).fraction, "log", "", (0.0, 1.0)))
            out.append(("blood_saturation", lambda t, at=at: at(t).saturation, "identity", "", (0.0, 1.0)))
        elif isinstance(ab, Fluorophore):
            names = {ab.name} | ({SHORT_NAMES[ab.name]} if ab.name in SHORT_NAMES else set())
            for nm in sorted(names):
                out.append((f"c_{nm}", lambda t, at=at: at(t).c, "log", "x 10 uM" if nm in ("ppix", "protoporphyrin_ix") else ""))
                out.append((f"yield_{nm}", lambda t, at=at: at(t).quantum_yield, "log", ""))
        elif isinstance(ab, TabulatedAbsorber):
            out.append((f"conc_{n_tab}", lambda t, at=at: at(t).concentration, "log", "M"))
            n_tab += 1
    sc = optics.scattering
    if isinstance(sc, ConstantScattering):
        out.append(("mus", lambda t: get(t).scattering.mus, "log", "1/cm"))
        out.append(("g", lambda t: get(t).scattering.g, "logit-g", ""))
    elif isinstance(sc, PowerLawScattering):
        out.append(("a", lambda t: get(t).scattering.a, "log", "1/cm"))
        out.append(("b", lambda t: get(t).scattering.b, "identity", ""))
        out.append(("g", lambda t: get(t).scattering.g, "logit-g", ""))
    return out


def scene_parameters(tissue) -> dict[str, FitParameter]:
    """Every parameter `--free` can name in `tissue`, by its full name ("layer0.mua", ...)."""
    table = {}
    for i, layer in enumerate(tissue.layers):
        for field, where, transform, units, *bounds in _optics_fields(layer, lambda t, i=i: t.layers[i]):
            table[f"layer{i}.{field}"] = FitParameter(f"layer{i}.{field}", where, transform, *bounds, units=units)
    for j, region in enumerate(tissue.regions):
        for field, where, transform, units, *bounds in _optics_fields(region.optics, lambda t, j=j: t.regions[j].optics):
            table[f"region{j}.{field}"] = FitParameter(f"region{j}.{field}", where, transform, *bounds, units=units)
    return table


def parameters_from_names(tissue, names) -> list[FitParameter]:
    """FitParameters for `names` (full "layer0.mua" or a bare field naming one medium); a
    `ValueError` lists what is available when a name is unknown or ambiguous."""
    table = scene_parameters(tissue)
    out = []
    for raw in names:
        name = raw.strip()
        if name in table:
            out.append(table[name])
            continue
        matches = [k for k in table if k.split(".", 1)[1] == name]
        if len(matches) == 1:
            out.append(table[matches[0]])
            continue
        available = ", ".join(table) or "(none)"
        if matches:
            raise ValueError(f"--free {name!r} is ambiguous: it names {', '.join(matches)}; use the full name")
        raise ValueError(f"--free {name!r} is not a parameter of this scene; available: {available}")
    full = [p.name for p in out]
    if len(set(full)) != len(full):
        raise ValueError(f"--free names a parameter twice: {full}")
    return out


def initial_values(tissue, assignments: str):
    """`tissue` with "name=value[,name=value...]" set (the command line's `--init`: an initial guess
    other than the scene's values; names as for `--free`, a value fills the whole leaf)."""
    for item in (a.strip() for a in assignments.split(",")):
        if not item:
            continue
        name, sep, text = item.partition("=")
        if not sep:
            raise ValueError(f"--init {item!r}: expected name=value")
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"--init {name.strip()}={text!r}: the value is not a number") from None
        (p,) = parameters_from_names(tissue, [name])
        leaf = p.where(tissue)
        lo, hi = p.interval
        if not lo < value < hi and not (p.transform == "identity" and p.bounds is None):
            raise ValueError(f"--init {p.name} = {value:g} {p.units}".rstrip() + f"; allowed ({lo:g}, {hi:g})")
        tissue = eqx.tree_at(p.where, tissue, jnp.full(jnp.shape(leaf), value, jnp.float64))
    return tissue
