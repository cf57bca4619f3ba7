"""`tissuefit check SCENE|STACK`: validate a scene file or a stack without running anything."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import io
from ._common import load
from ._main import InvalidInput

STACK_SUFFIXES = (".tif", ".tiff", ".json")


def check_stack(path: Path) -> int:
    """Read and validate a stack (data_spec/stack.md) and print its shape, bands, units and range."""
    try:
        stack = io.read_stack(path)
    except ValueError as err:
        raise InvalidInput(str(err)) from None
    bands, h, w = stack.data.shape
    finite = stack.data[np.isfinite(stack.data)]
    print(f"ok: {stack.kind} stack, {bands} bands {stack.wavelengths[0]:g}–{stack.wavelengths[-1]:g} nm, "
          f"{w} x {h} pixels, {stack.units}; samples {float(finite.min()):.4g} .. {float(finite.max()):.4g}")
    return 0


def run(args) -> int:
    if Path(args.scene).suffix.lower() in STACK_SUFFIXES:
        return check_stack(Path(args.scene))
    runs = load(args.scene)
    print(f"ok: {len(runs)} run(s)")
    for r in runs:
        if isinstance(r, io.SpectralRun):
            from ..scene import Fluorophore

            tissue = r.scene.tissue
            centres = tissue.bands.centers
            optics = tissue.layers + tuple(region.optics for region in tissue.regions)
            fluorophores = sum(isinstance(a, Fluorophore) for m in optics for a in m.absorbers)
            print(f"  {r.name}: spectral, {len(centres)} bands {centres[0]:g}–{centres[-1]:g} nm, "
                  f"{tissue.num_layers} layer(s), {len(tissue.regions)} region(s), {fluorophores} fluorophore(s)")
            if r.render is not None:
                endo = r.render.endoscope
                print(f"    render: {endo.width} x {endo.height} pixels, beta {endo.beta_deg:g} deg, "
                      f"{r.render.photons} photons")
    return 0
