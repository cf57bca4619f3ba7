"""A run: one simulation a file asks for (scene, photon count, tallies, options, seed).

`Run` is a single-band simulation (`trace`); `SpectralRun` a multi-spectral one (`trace_spectral`),
which may also carry a `RenderSpec` (its `[endoscope]` and `[render]` tables, for `render`).
"""

from __future__ import annotations

import json
from typing import Literal

import equinox as eqx

from .._checks import check_positive_int
from ..render import Endoscope, RenderOptions
from ..scene import Scene, SpectralScene
from ..transport import RecordSpec, SpectralOptions, TallySpec, TraceOptions

MAX_PHOTONS = 2**32 - 1
"""Largest photon count a run may ask for (photon indices are 32-bit)."""


class Run(eqx.Module):
    """One simulation read from a scene file (`.toml`) or one run of an MCML input file (`.mci`).

    Fields:
    - `name`: label used for output files (`<name>.json`).
    - `scene`: the tissue and the source.
    - `photons`: number of photon packets to launch, 1 .. `MAX_PHOTONS`.
    - `tallies`, `options`: what to tally and how to trace (static trace config).
    - `seed`: PRNG seed, or None when the file gives none (the CLI then uses a fixed default).
    - `source_file`: the file the run was read from.
    - `mco_output`: the output file name an `.mci` run names (None for `.toml` scenes).
    - `mco_format`: MCML's output format letter for that file, "A" (ASCII) or "B"; None for `.toml`.

    A Run is plain data for files and the CLI; the simulator only sees `scene`, `tallies` and
    `options`. Use `dataclasses.replace(run, photons=...)` to override a field.
    """

    name: str = eqx.field(static=True)
    scene: Scene
    photons: int = eqx.field(static=True)
    tallies: TallySpec = eqx.field(static=True, default_factory=TallySpec)
    options: TraceOptions = eqx.field(static=True, default_factory=TraceOptions)
    seed: int | None = eqx.field(static=True, default=None)
    source_file: str = eqx.field(static=True, default="<memory>")
    mco_output: str | None = eqx.field(static=True, default=None)
    mco_format: Literal["A", "B"] | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        check_positive_int("run.photons", self.photons, high=MAX_PHOTONS)
        if self.seed is not None and (isinstance(self.seed, bool) or not isinstance(self.seed, int)):
            raise TypeError(f"run.seed = {self.seed!r} must be an integer or None")
        if self.mco_format not in (None, "A", "B"):
            raise ValueError(f"mco_format = {self.mco_format!r}; allowed 'A', 'B' or None")


DEFAULT_RENDER_PHOTONS = 300_000
"""Photons a render launches when `[render]` gives no `photons` (the paper's count per map)."""


class RenderSpec(eqx.Module):
    """What `tissuefit render` does with a spectral scene: the `[endoscope]` and `[render]` tables.

    Fields:
    - `endoscope`: the head's geometry (`tissuefit.render.Endoscope`).
    - `options`: how radiance is estimated (`tissuefit.render.RenderOptions`).
    - `photons`: photons launched from the lights, 1 .. `MAX_PHOTONS` (default 300 000).
    - `seed`: the render's PRNG seed, or None (then the command line's, else `SpectralRun.seed`, else 0).
    - `observation_filter`: the camera's filter (a spectrum of transmissions) or None;
      `observation_filter_doc`: its `[render.observation_filter]` table as JSON text (for echoes).

    Plain data; use `dataclasses.replace` to override a field.
    """

    endoscope: Endoscope = eqx.field(static=True, default_factory=Endoscope)
    options: RenderOptions = eqx.field(static=True, default_factory=RenderOptions)
    photons: int = eqx.field(static=True, default=DEFAULT_RENDER_PHOTONS)
    seed: int | None = eqx.field(static=True, default=None)
    observation_filter: object = None
    observation_filter_doc: str | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        check_positive_int("render.photons", self.photons, high=MAX_PHOTONS)
        if self.seed is not None and (isinstance(self.seed, bool) or not isinstance(self.seed, int)):
            raise TypeError(f"render.seed = {self.seed!r} must be an integer or None")
        if not isinstance(self.endoscope, Endoscope):
            raise TypeError(f"render.endoscope is a {type(self.endoscope).__name__}, not an Endoscope")
        if not isinstance(self.options, RenderOptions):
            raise TypeError(f"render.options is a {type(self.options).__name__}, not RenderOptions")


class SpectralRun(eqx.Module):
    """One multi-spectral simulation read from a scene file that uses spectral features
    (data_spec/scene.md, "Spectral scenes"); traced by `trace_spectral`.

    Fields:
    - `name`, `photons`, `options`, `seed`, `source_file`: as in `Run`.
    - `scene`: the `SpectralScene` (bands, spectral layers, regions, source and its spectrum).
    - `spectral`: `SpectralOptions` (mode, conversion boost); `records`: `RecordSpec` (photon records).
    - `document`: the resolved scene part of the file (ambient, bands, layers, regions, source),
      as JSON text: defaults filled in, file names absolute. `scene_to_dict` adds the run settings
      from the fields above, so command-line overrides are echoed too.
    - `input_files`: (absolute path, sha256) of every table and EEM file the scene read.
    - `render`: the file's `[endoscope]` and `[render]` tables as a `RenderSpec`, or None when it has
      neither (`tissuefit render` then uses `RenderSpec()`); `scene_to_dict` echoes them when present.
    - `source_sha256`: SHA-256 of the scene file's bytes (None for a document not read from a file).

    Plain data for files and the CLI; use `dataclasses.replace(run, photons=...)` to override a field.
    """

    name: str = eqx.field(static=True)
    scene: SpectralScene
    photons: int = eqx.field(static=True)
    options: TraceOptions = eqx.field(static=True, default_factory=TraceOptions)
    spectral: SpectralOptions = eqx.field(static=True, default_factory=SpectralOptions)
    records: RecordSpec = eqx.field(static=True, default_factory=RecordSpec)
    seed: int | None = eqx.field(static=True, default=None)
    source_file: str = eqx.field(static=True, default="<memory>")
    document: str = eqx.field(static=True, default="{}")
    input_files: tuple[tuple[str, str], ...] = eqx.field(static=True, default=())
    render: RenderSpec | None = None  # not static: its observation filter holds arrays
    source_sha256: str | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        check_positive_int("run.photons", self.photons, high=MAX_PHOTONS)
        if self.seed is not None and (isinstance(self.seed, bool) or not isinstance(self.seed, int)):
            raise TypeError(f"run.seed = {self.seed!r} must be an integer or None")
        if not isinstance(json.loads(self.document), dict):
            raise ValueError("SpectralRun.document must be the JSON text of a table (object)")
