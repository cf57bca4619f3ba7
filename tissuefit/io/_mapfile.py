"""Parameter-map files (data_spec/maps.md): a float32 TIFF of a `MapResult`'s layers with a JSON
sidecar, a JSON summary and a PNG of the maps with colour bars and units, each written atomically."""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path

import numpy as np

from .._atomic import atomic_writer, write_text_atomic
from ..maps import FLAG_BITS, MAPS_FORMAT, MapResult


def write_maps(folder, result: MapResult, *, extra: dict | None = None, png: bool = True) -> list[Path]:
    """Write `maps.tif` + `maps.json` (the layer stack and its sidecar), `summary.json` and
    (`png`) `maps.png` into `folder` (data_spec/maps.md). Returns the paths written."""
    import tifffile

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    layers = result.layers()
    stack = np.ascontiguousarray(np.stack([np.asarray(img, np.float32) for *_, img in layers]))
    buf = io.BytesIO()
    tifffile.imwrite(buf, stack, photometric="minisblack")
    payload = buf.getvalue()
    tif, side, summ = folder / "maps.tif", folder / "maps.json", folder / "summary.json"
    with atomic_writer(tif, binary=True) as handle:
        handle.write(payload)
    summary = _clean(result.summary() | (extra or {}))
    sidecar = dict(format=MAPS_FORMAT, image=tif.name, image_sha256=hashlib.sha256(payload).hexdigest(),
                   shape=list(stack.shape), dtype="float32",
                   layers=[dict(index=i, name=n, kind=k, units=u) for i, (n, k, u, _) in enumerate(layers)],
                   flag_bits=FLAG_BITS, summary=summary)
    write_text_atomic(side, json.dumps(sidecar, indent=2, allow_nan=False) + "\n")
    write_text_atomic(summ, json.dumps(summary, indent=2, allow_nan=False) + "\n")
    files = [tif, side, summ]
    if png:
        with atomic_writer(folder / "maps.png", binary=True) as handle:
            handle.write(maps_png(result))
        files.append(folder / "maps.png")
    return files


def read_maps(path) -> tuple[dict, np.ndarray]:
    """(sidecar, layers [L, H, W] float32) of `maps.json` or `maps.tif`; checks format and SHA-256."""
    import tifffile

    path = Path(path)
    side = path.with_suffix(".json")
    doc = json.loads(side.read_text())
    if doc.get("format") != MAPS_FORMAT:
        raise ValueError(f"{side}: format = {doc.get('format')!r}; expected {MAPS_FORMAT!r}")
    payload = (side.parent / doc["image"]).read_bytes()
    if hashlib.sha256(payload).hexdigest() != doc["image_sha256"]:
        raise ValueError(f"{side}: image_sha256 does not match {doc['image']}")
    data = tifffile.imread(io.BytesIO(payload))
    if list(data.shape) != doc["shape"]:
        raise ValueError(f"{side}: shape {doc['shape']} but the image is {list(data.shape)}")
    return doc, data


def _clean(v):
    if isinstance(v, dict):
        return {str(k): _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    if isinstance(v, (float, np.floating)):
        return float(v) if np.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.ndarray):
        return _clean(v.tolist())
    return v


def maps_png(result: MapResult, *, dpi: int = 110) -> bytes:
    """PNG: per parameter its map and its sigma map (flagged pixels grey), then the residual RMS
    and the flags; each panel with a colour bar and units."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = len(result.names)
    cols = max(p, 2)
    fig, axes = plt.subplots(3, cols, figsize=(3.2 * cols, 8.4), squeeze=False)
    good = result.good
    for k, (name, unit) in enumerate(zip(result.names, result.units)):
        for row, (img, what) in enumerate(((result.values[k], name), (result.sigma[k], f"sigma({name})"))):
            ax = axes[row, k]
            data = np.where(good, img, np.nan)
            finite = data[np.isfinite(data)]
            lo, hi = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
            cmap = matplotlib.colormaps["viridis"].with_extremes(bad="0.6")
            im = ax.imshow(data, cmap=cmap, vmin=lo, vmax=hi if hi > lo else lo + 1e-12)
            ax.set_title(what, fontsize=9)
            ax.set_xticks([])
            ax.set_yticks([])
            bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
            bar.set_label(unit if unit and unit != "-" else "(dimensionless)", fontsize=8)
            bar.ax.tick_params(labelsize=7)
    for k in range(p, cols):
        axes[0, k].axis("off")
        axes[1, k].axis("off")
    ax = axes[2, 0]
    rms = np.where(good, result.residual_rms, np.nan)
    finite = rms[np.isfinite(rms)]
    im = ax.imshow(rms, cmap=matplotlib.colormaps["magma"].with_extremes(bad="0.6"), vmin=0,
                   vmax=float(np.percentile(finite, 99)) if finite.size else 1.0)
    ax.set_title("residual RMS", fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
    bar.set_label("noise sigmas", fontsize=8)
    ax = axes[2, 1]
    # each flagged pixel in the colour of its lowest set bit; good pixels white
    flags = result.flags.astype(np.int64)
    lowest = np.full(flags.shape, np.nan)
    for bit in (3, 2, 1, 0):
        lowest = np.where(flags & (1 << bit), float(bit), lowest)
    colours = matplotlib.colors.ListedColormap(["tab:red", "tab:orange", "tab:purple", "tab:gray"]).with_extremes(bad="white")
    im = ax.imshow(lowest, cmap=colours, vmin=-0.5, vmax=3.5, interpolation="nearest")
    ax.set_title(f"flags ({int((~good).sum())} of {good.size} pixels)", fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03, ticks=[0, 1, 2, 3])
    bar.ax.set_yticklabels(["not converged", "at bound", "singular", "masked"], fontsize=7)
    for k in range(2, cols):
        axes[2, k].axis("off")
    fig.suptitle(f"tissuefit map: {result.flags.shape[1]} x {result.flags.shape[0]} pixels, {result.seconds:.1f} s",
                 fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    return buf.getvalue()
