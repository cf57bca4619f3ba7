"""Photon records: what the tracer hands to the photon maps (docs/design.md §7).

Two kinds, each in a fixed-size buffer whose capacity is chosen before `jit` (static):
- surface records: one per photon leaving the tissue through the top face (z = 0), at the exit
  point, with the direction *outside* the tissue (pointing up, uz < 0);
- volume records: one per interaction of a converted (fluorescent) photon inside the tissue,
  at the interaction point (z > 0, depth below the surface), with the direction the photon had
  *arriving* at the interaction (the direction a phase function is evaluated against).
  With `RecordSpec.volume_all`, non-converted photons' interactions are recorded too. With
  `RecordSpec.emission`, every conversion point is recorded as well, as an *emission* record: the
  power the photon leaves with (isotropically) after the conversion, `emission = True`. Arrival
  records estimate the collision density (mut x radiance); emission records the fluorescence
  source. A renderer's in-scattered radiance needs both (see `tissuefit.render`).

Coordinates: tissue surface at z = 0, depth z > 0 downward (MCML's convention), all in cm.
Powers are per launched photon (a record's `power` summed over all records of a kind gives the
corresponding tally: surface powers sum to rd per band; volume arrival powers sum to the weight
arriving at interactions; emission powers sum to the emitted fluorescence per band).

Path statistics: each record carries the path length `path` [cm] and the number of scattering
interactions `hits` the photon made in each medium (layers first, then region media, as
`SpectralTissue.properties()` orders them) since its launch or its last conversion: the current
segment, with whose optical properties its power is an explicit function (docs/design.md §5).
Buffers fill in photon-index order within each device's photon range, so a run
is reproducible; when a buffer is full, further records are counted in `overflow` and dropped —
never silently.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._checks import check_positive_int


class RecordSpec(eqx.Module):
    """Which photon records to keep and how many (static; changing it recompiles).

    - `surface`: capacity of the surface buffer (0 = no surface records; the default).
    - `volume`: capacity of the volume buffer (0 = none; the default).
    - `volume_all`: record interactions of non-converted photons too (default: converted only).
    - `emission`: record every conversion point as an emission record in the volume buffer
      (default off; the renderer turns it on).
    - `arrivals`: record interactions (arrival records) in the volume buffer (default on); off
      with `emission` on keeps the conversion points alone (`tissuefit.maps`' fluorescence tables
      need where photons converted, not the hundreds of interactions after).
    - `replay`: records carry what replaying them at other parameters needs (`tissuefit.replay`):
      the Henyey–Greenstein score per medium and, for converted photons, the statistics of the
      excitation segment before their conversion (path, hits, score, medium, and its band per band
      or, on shared paths, the band weights the photon arrived at the conversion with). Default off.
    The paper keeps 300 000 of each. Records are off unless a consumer asks for them.
    """

    surface: int = eqx.field(static=True, default=0)
    volume: int = eqx.field(static=True, default=0)
    volume_all: bool = eqx.field(static=True, default=False)
    emission: bool = eqx.field(static=True, default=False)
    arrivals: bool = eqx.field(static=True, default=True)
    replay: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        for name in ("surface", "volume"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 0:
                raise ValueError(f"records.{name} = {value!r}; allowed an integer in [0, 2^31 - 1] (buffer capacity, records)")
            if value:
                check_positive_int(f"records.{name}", value, high=2**31 - 1)
        for name in ("volume_all", "emission", "arrivals", "replay"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"records.{name} = {getattr(self, name)!r} must be True or False")

    @property
    def any(self) -> bool:
        return self.surface > 0 or self.volume > 0


class PhotonRecords(eqx.Module):
    """One buffer of photon records (numpy arrays after a trace; rows >= `count` are padding).

    - `position` [capacity, 3] cm: (x, y, z), z >= 0 depth below the surface.
    - `direction` [capacity, 3]: unit vector (see the module docstring for which direction).
    - `power` [capacity, bands]: power per band per launched photon [-] (photon counts: emitted
      fluorescence carries the quantum yield, not the Stokes energy factor).
    - `band` [capacity] int: the band whose optical properties carried the photon when recorded.
    - `converted` [capacity] bool: the photon had been converted (fluorescence) when recorded.
    - `emission` [capacity] bool: an emission record (a conversion point; isotropic emission).
    - `photon` [capacity] int: the index of the photon that made the record.
    - `path` [capacity, media] cm and `hits` [capacity, media]: path length and scattering
      interactions per medium since launch or the last conversion (see the module docstring).
    - `count`: valid rows; `overflow`: records dropped because the buffer was full.
    With `RecordSpec.replay` (else None): `score` [capacity, media], the sum of d log p_HG/dg over
    the segment's scatterings per medium; for converted records the excitation segment before the
    last conversion: `path0`, `hits0`, `score0` [capacity, media], its band `band0` (per-band
    traces) or, on shared paths, `exc0` [capacity, bands], the band weights the photon arrived at
    the conversion with (largest 1; the excitation spectrum its emission mixes), the medium
    `conv_medium` the conversion happened in, and `conversions`, how many conversions the photon
    made (a record with more than one has an excitation history older than `path0`; see
    `tissuefit.replay`).
    """

    position: Float[Array, "capacity 3"]
    direction: Float[Array, "capacity 3"]
    power: Float[Array, "capacity bands"]
    band: Int[Array, " capacity"]
    converted: Bool[Array, " capacity"]
    photon: Int[Array, " capacity"]
    count: int
    overflow: int
    emission: Bool[Array, " capacity"] | None = None
    path: Float[Array, "capacity media"] | None = None
    hits: Float[Array, "capacity media"] | None = None
    score: Float[Array, "capacity media"] | None = None
    path0: Float[Array, "capacity media"] | None = None
    hits0: Float[Array, "capacity media"] | None = None
    score0: Float[Array, "capacity media"] | None = None
    band0: Int[Array, " capacity"] | None = None
    exc0: Float[Array, "capacity bands"] | None = None
    conv_medium: Int[Array, " capacity"] | None = None
    conversions: Int[Array, " capacity"] | None = None

    @property
    def capacity(self) -> int:
        return int(self.position.shape[0])

    def valid(self) -> "PhotonRecords":
        """The first `count` rows only (numpy slices)."""
        n = int(self.count)
        return self.select(np.arange(self.capacity) < n)

    def select(self, mask) -> "PhotonRecords":
        """The rows where `mask` [capacity] is true, as a packed buffer (numpy; `count` = rows kept,
        `overflow` carried over). E.g. `records.select(~records.emission)`."""
        mask = np.asarray(mask, bool) & (np.arange(self.capacity) < int(self.count))
        cut = lambda a: None if a is None else np.asarray(a)[mask]  # noqa: E731
        return PhotonRecords(count=int(mask.sum()), overflow=int(self.overflow),
                             **{f: cut(getattr(self, f)) for f in ROW_FIELDS})

    def padded(self, rows: int) -> "PhotonRecords":
        """The same records in a buffer of `rows` >= capacity (numpy; the extra rows are zero
        padding beyond `count`), with `count` as a 0-d array: buffers padded to a few sizes give
        arrays of a few shapes, so that functions compiled on them (a fit's replay, `update_map`)
        are reused between traces whose record counts differ."""
        rows = check_positive_int("rows", rows, high=2**40)
        if rows < self.capacity:
            raise ValueError(f"rows = {rows}; allowed at least the buffer's capacity {self.capacity}")

        def pad(a):
            if a is None:
                return None
            a = np.asarray(a)
            return np.concatenate([a, np.zeros((rows - a.shape[0], *a.shape[1:]), a.dtype)])

        return PhotonRecords(count=np.asarray(int(self.count), np.int64), overflow=int(self.overflow),
                             **{f: pad(getattr(self, f)) for f in ROW_FIELDS})


REPLAY_FIELDS = ("score", "path0", "hits0", "score0", "band0", "exc0", "conv_medium", "conversions")
"""Record fields kept with `RecordSpec.replay` (None otherwise)."""

ROW_FIELDS = ("position", "direction", "power", "band", "converted", "photon", "emission", "path", "hits",
              *REPLAY_FIELDS)
"""Every per-record field (one row per record; `select` and `padded` carry each of them)."""


TINY = 1e-30
"""Floor [1/cm] under mus in log(mus/mus0): a replay at mus -> 0 stays finite (the ratio tends to 0)."""


def segment_log_ratio(path, hits, score, props, props0) -> Float[Array, "n bands"]:
    """log of a segment's weight ratio in every band: sum_m n_m log(mus/mus0) - L_m (mut - mut0)
    + S_m (g - g0), with path [cm], hits, score [n, media] and props (mua [1/cm], mus [1/cm], g)
    [media, bands] at the new and the traced parameters.

    The likelihood ratio belongs to `tissuefit.replay`, which re-exports this function for recorded
    segments. It is defined here because the next-event camera image (`_nee.py`) scores its
    contributions on the fly and never records them, so there is nothing to replay afterwards: the
    tracer scores their tangents itself (docs/design.md §5), and transport cannot import replay."""
    (mua, mus, g), (mua0, mus0, g0) = props, props0
    log_mus = jnp.where(mus0 > 0, jnp.log(jnp.maximum(mus, TINY) / jnp.where(mus0 > 0, mus0, 1.0)), 0.0)
    dmut = (mua + mus) - (mua0 + mus0)
    out = hits @ log_mus - path @ dmut
    if score is not None:
        out = out + score @ (g - g0)
    return out
