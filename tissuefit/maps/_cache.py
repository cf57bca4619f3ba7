"""Built white Monte Carlo models on disk, keyed by everything they depend on, written atomically.

A model depends on its nodes (g, n), photons, seed, a_floor, the tabulation grids and the tracer
that made it: the key hashes those settings and the source of tissuefit/transport and of the
builder, so a changed tracer never serves an old table. Models live in
`<cache>/maps/white-<key>.npz`, beside the compilation cache (`tissuefit.default_cache_dir()`'s
parent; `TISSUEFIT_CACHE_DIR=off` turns both off), written to a temporary file and renamed.
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
from pathlib import Path

import numpy as np

from .._atomic import atomic_writer
from . import _fluorescence, _lighting
from ._build import A_FLOOR, COS_EDGES, LOG_A, build_node, check_node
from ._model import WhiteModel

FORMAT = "tissuefit-white-mc/3"
FLUORESCENCE_PHOTONS = 50_000
"""Default photons of a node's fluorescence trace (half analog, half boosted; `_fluorescence.py`)."""


@functools.lru_cache(maxsize=1)
def _source_hash() -> str:
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for f in sorted([*(root / "transport").glob("*.py"), root / "maps" / "_build.py", root / "maps" / "_fluorescence.py",
                         root / "maps" / "_lighting.py"]):
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def model_key(g_nodes, n_nodes, *, photons: int, seed: int, a_floor: float, fluorescence: int = 0,
              lighting: bool = False) -> str:
    """The cache key (hex) of a model with these settings and this tracer (`fluorescence`: the
    fluorescence trace's photons, 0 = none; `lighting`: with the lighting tables)."""
    doc = dict(format=FORMAT, g=[round(float(g), 6) for g in g_nodes], n=[round(float(n), 6) for n in n_nodes],
               photons=int(photons), seed=int(seed), a_floor=float(a_floor), log_a=list(LOG_A),
               cos_edges=list(COS_EDGES), source=_source_hash(), fluorescence=int(fluorescence),
               depth=list(_fluorescence.DEPTH), log_a_f=list(_fluorescence.LOG_A_F), boost=_fluorescence.BOOST,
               lighting=bool(lighting), incidence=list(_lighting.INCIDENCE_DEG), log_a_l=list(_lighting.LOG_A_L),
               rho=list(_lighting.RHO_EDGES))
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:24]


def default_model_dir() -> Path | None:
    from .._setup import default_cache_dir

    base = default_cache_dir()
    return None if base is None else base.parent / "maps"


def _save(path: Path, model: WhiteModel, key: str) -> None:
    buf = io.BytesIO()
    fl = ({} if not model.fluorescent else
          dict(fl_source=model.fl_source, fl_escape=model.fl_escape, fl_rel_variance=model.fl_rel_variance))
    if model.lit:
        fl.update(lit_q0=model.lit_q0, lit_q1=model.lit_q1)
    np.savez(buf, grid=model.grid, log_value=model.log_value, log_slope=model.log_slope,
             rel_variance=model.rel_variance, eps=model.eps, **fl,
             meta=np.frombuffer(json.dumps(dict(format=FORMAT, key=key, g_nodes=model.g_nodes, n_nodes=model.n_nodes,
                                                photons=model.photons, a_floor=model.a_floor, seed=model.seed,
                                                cos_edges=model.cos_edges, fl_photons=model.fl_photons,
                                                lit_photons=model.lit_photons)).encode(),
                                np.uint8))
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_writer(path, binary=True) as handle:
        handle.write(buf.getvalue())


def _load(path: Path, key: str) -> WhiteModel | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(bytes(z["meta"]).decode())
            if meta.get("format") != FORMAT or meta.get("key") != key:
                return None
            return WhiteModel(g_nodes=tuple(meta["g_nodes"]), n_nodes=tuple(meta["n_nodes"]),
                              cos_edges=tuple(meta["cos_edges"]), photons=int(meta["photons"]),
                              a_floor=float(meta["a_floor"]), seed=int(meta["seed"]), grid=z["grid"],
                              grid_spec=(float(z["grid"][0]), float(z["grid"][1] - z["grid"][0]), int(z["grid"].size)),
                              log_value=z["log_value"], log_slope=z["log_slope"], rel_variance=z["rel_variance"],
                              eps=z["eps"], fl_photons=int(meta.get("fl_photons", 0)),
                              lit_photons=int(meta.get("lit_photons", 0)),
                              **{k: z[k] for k in ("fl_source", "fl_escape", "fl_rel_variance", "lit_q0", "lit_q1")
                                 if k in z.files}
                              ).with_integral()
    except (OSError, ValueError, KeyError):
        return None  # unreadable or stale: rebuilt (and overwritten) by the caller


def build_model(g_nodes=(0.9,), n_nodes=(1.4,), *, photons: int = 50_000, seed: int = 0, a_floor: float = A_FLOOR,
                fluorescence: int | bool = False, lighting: bool = False, cache: str | Path | bool | None = True,
                progress=None) -> WhiteModel:
    """A `WhiteModel` on the (g, n) nodes: read from the cache when built before, else traced
    (one white Monte Carlo trace of `photons` photons per node; about 20 s per node at g = 0.9 on
    2 CPU cores, longer at higher g) and cached. `fluorescence`: also the fluorescence tables, from
    a trace of that many photons per node (True: `FLUORESCENCE_PHOTONS`; False/0: none).
    `lighting`: also the lighting tables (`_lighting.py`, for oblique, non-uniform light such as an
    endoscope's), from `photons` photons at each oblique incidence angle (the normal one is the
    reflectance's trace; about 30 s more per node at g = 0.9 on 2 idle CPU cores).
    `cache`: True (the default folder, `default_model_dir()`), a folder, or False/None (no cache).
    `progress(text)` hears each node."""
    fl_photons = FLUORESCENCE_PHOTONS if fluorescence is True else int(fluorescence or 0)
    lit_photons = int(photons) if lighting else 0
    g_nodes = tuple(sorted({check_node(g, 1.4)[0] for g in np.atleast_1d(g_nodes)}))
    n_nodes = tuple(sorted({check_node(0.5, n)[1] for n in np.atleast_1d(n_nodes)}))
    key = model_key(g_nodes, n_nodes, photons=photons, seed=seed, a_floor=a_floor, fluorescence=fl_photons,
                    lighting=bool(lighting))
    folder = default_model_dir() if cache is True else (Path(cache) if cache else None)
    path = None if folder is None else folder / f"white-{key}.npz"
    if path is not None and path.exists():
        model = _load(path, key)
        if model is not None:
            return model
    tables, fl_tables, lit_tables = [], [], []
    for g in g_nodes:
        row, fl_row, lit_row = [], [], []
        for n in n_nodes:
            table, traced = build_node(g, n, photons=photons, seed=seed, a_floor=a_floor)
            row.append(table)
            if progress is not None:
                progress(f"white Monte Carlo node g = {g:g}, n = {n:g}: {row[-1]['seconds']:.1f} s")
            if fl_photons:
                fl_row.append(_fluorescence.build_fluorescence_node(g, n, photons=fl_photons, seed=seed, a_floor=a_floor,
                                                                    cos_edges=COS_EDGES))
                if progress is not None:
                    progress(f"  fluorescence: {fl_row[-1]['conversions']} conversions, {fl_row[-1]['seconds']:.1f} s")
            if lit_photons:
                lit_row.append(_lighting.build_lighting_node(g, n, photons=lit_photons, seed=seed, a_floor=a_floor,
                                                             normal=traced))
                if progress is not None:
                    progress(f"  lighting: {len(_lighting.INCIDENCE_DEG)} incidence angles, {lit_row[-1]['seconds']:.1f} s")
        tables.append(row)
        fl_tables.append(fl_row)
        lit_tables.append(lit_row)
    model = WhiteModel.from_tables(tables, g_nodes=g_nodes, n_nodes=n_nodes, photons=photons, a_floor=a_floor, seed=seed,
                                   fluorescence=fl_tables if fl_photons else None, fl_photons=fl_photons,
                                   lighting=lit_tables if lit_photons else None, lit_photons=lit_photons)
    if path is not None:
        _save(path, model, key)
    return model


def model_for_tissue(tissue, **kwargs) -> WhiteModel:
    """The model for the top layer of a `SpectralTissue`: its g (which must be the same in every
    band) and n, one node (exact: no interpolation), with fluorescence tables when the layer has a
    fluorophore (unless `fluorescence` is given)."""
    from ..scene import Fluorophore

    kwargs.setdefault("fluorescence", any(isinstance(a, Fluorophore) for a in tissue.layers[0].absorbers))
    _, _, g = tissue.properties()
    g = np.asarray(g)[0]
    if np.ptp(g) > 1e-9:
        raise ValueError(f"tissue layer 0: g varies across bands ({g.min():g}..{g.max():g}); the white Monte Carlo "
                         "model needs one g per layer")
    return build_model((float(g[0]),), (float(tissue.geometry.n[0]),), **kwargs)
