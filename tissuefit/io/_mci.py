"""MCML's input format (.mci), as described in Wang & Jacques (1992), "MCML — Monte Carlo modeling
of photon transport in multi-layered tissues: user manual".

Layout (one value group per data line; `#` starts a comment; blank and comment lines are skipped):

    1.0                       # file version
    2                         # number of runs
    # then, for each run:
    sample.mco A              # output file name, format letter (A = ASCII, B)
    1000000                   # number of photons
    0.01 0.01                 # dz, dr [cm]
    40 50 1                   # nz, nr, na (numbers of depth, radius, angle bins)
    3                         # number of layers
    1                         # n of the medium above
    1.37 1 100 0.9 0.1        # one line per layer: n, mua [1/cm], mus [1/cm], g, d [cm]
    1                         # n of the medium below

Every value is checked before anything runs; errors name the file, the line, the field, the value
and the allowed range with its unit. Our ranges are the scene constructors' (n >= 1, -1 < g < 1,
thickness > 0), stricter than MCML's own (n > 0, 0 <= g <= 1, d >= 0). One extension: the last
layer's thickness may be `inf` (semi-infinite). Integers must be written as integers (MCML would
read `1e6` photons as 1).
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

from .._checks import check_range
from ..scene import LayeredTissue, PencilBeam, Scene
from ..transport import TALLY_NAMES, TallySpec, TraceOptions
from ._run import MAX_PHOTONS, Run

_INT = re.compile(r"[+-]?\d+")
_FLOAT = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")
_INF = re.compile(r"\+?inf(inity)?", re.IGNORECASE)


@dataclasses.dataclass(frozen=True)
class _Line:
    number: int
    tokens: list[str]


class _DataLines:
    """The data lines of a text file in MCML's style: `#` comments and blank lines skipped."""

    def __init__(self, path: str, text: str):
        self.path = path
        self._lines: list[_Line] = []
        for number, raw in enumerate(text.splitlines(), start=1):
            tokens = raw.split("#", 1)[0].split()
            if tokens:
                self._lines.append(_Line(number, tokens))
        self._next = 0
        self._last_number = len(text.splitlines())

    def peek(self) -> _Line | None:
        return self._lines[self._next] if self._next < len(self._lines) else None

    def take(self, what: str) -> _Line:
        if self._next >= len(self._lines):
            raise ValueError(f"{self.path}:{self._last_number}: missing line: expected {what}, found end of file")
        line = self._lines[self._next]
        self._next += 1
        return line

    def error(self, line: _Line, message: str) -> ValueError:
        return ValueError(f"{self.path}:{line.number}: {message}")


def _tokens(lines: _DataLines, line: _Line, names: list[str], *, optional: int = 0) -> list[str]:
    """The tokens of `line`, which must hold len(names) values (the last `optional` may be missing)."""
    need, have = len(names), len(line.tokens)
    if have < need - optional:
        missing = ", ".join(names[have:])
        raise lines.error(line, f"expected {need} value(s) ({', '.join(names)}); missing {missing}")
    if have > need:
        junk = " ".join(line.tokens[need:])
        raise lines.error(line, f"unexpected extra value(s) {junk!r} after {', '.join(names)}")
    return line.tokens


def _int(lines: _DataLines, line: _Line, field: str, token: str, high: int | None = None) -> int:
    allowed = f"[1, {high}]" if high is not None else "[1, inf)"
    if not _INT.fullmatch(token):
        raise lines.error(line, f"{field} = {token!r} is not an integer; allowed {allowed}")
    value = int(token)
    if value < 1 or (high is not None and value > high):
        raise lines.error(line, f"{field} = {value} is out of range; allowed {allowed}")
    return value


def _float(lines: _DataLines, line: _Line, field: str, token: str, **bounds) -> float:
    """Parse `token` and check it with `check_range(field, ..., **bounds)`, prefixing file:line.

    `inf` is parsed (and then accepted only where `bounds` has `allow_inf`)."""
    allowed = _allowed(**bounds)
    if not (_FLOAT.fullmatch(token) or _INF.fullmatch(token)):
        raise lines.error(line, f"{field} = {token!r} is not a number; allowed {allowed}")
    value = float(token)
    try:
        check_range(field, value, **bounds)
    except ValueError as err:
        raise lines.error(line, str(err)) from None
    return value


def _allowed(*, unit, low=None, high=None, low_open=False, high_open=False, allow_inf=False) -> str:
    lo = "-inf" if low is None else f"{low:g}"
    hi = "inf" if high is None else f"{high:g}"
    text = f"{'(' if low_open or low is None else '['}{lo}, {hi}{')' if high_open or high is None else ']'}"
    text = text if unit == "-" else f"{text} {unit}"
    return text + (" (inf allowed)" if allow_inf else "")


_N = dict(unit="-", low=1.0)
_MU = dict(unit="1/cm", low=0.0)
_G = dict(unit="-", low=-1.0, high=1.0, low_open=True, high_open=True)
_LENGTH = dict(unit="cm", low=0.0, low_open=True)


@dataclasses.dataclass(frozen=True)
class InParm:
    """One run's input parameters as MCML writes them (the InParm block of .mci and .mco files)."""

    output: str
    format: str
    photons: int
    dz: float
    dr: float
    nz: int
    nr: int
    na: int
    n_above: float
    n_below: float
    layers: tuple[tuple[float, float, float, float, float], ...]  # n, mua, mus, g, d
    line: int  # line of the output-file entry, for messages

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        del out["line"]
        out["layers"] = [dict(zip(("n", "mua", "mus", "g", "thickness"), layer)) for layer in self.layers]
        return out


def read_inparm(lines: _DataLines, label: str) -> InParm:
    """Read one run's parameters (output name through n below) from `lines`; `label` prefixes fields."""
    line = lines.take("the output file name and format (e.g. 'sample.mco A')")
    tokens = _tokens(lines, line, ["output file name", "format A|B"], optional=1)
    output, fmt = tokens[0], (tokens[1] if len(tokens) > 1 else "A")
    if fmt.upper() not in ("A", "B"):
        raise lines.error(line, f"{label}output format = {fmt!r}; allowed 'A' (ASCII) or 'B'")
    first = line.number

    line = lines.take("the number of photons")
    photons = _int(lines, line, f"{label}photons", _tokens(lines, line, ["number of photons"])[0], high=MAX_PHOTONS)

    line = lines.take("dz, dr [cm]")
    dz_t, dr_t = _tokens(lines, line, ["dz [cm]", "dr [cm]"])
    dz = _float(lines, line, f"{label}tallies.dz", dz_t, **_LENGTH)
    dr = _float(lines, line, f"{label}tallies.dr", dr_t, **_LENGTH)

    line = lines.take("nz, nr, na")
    nz_t, nr_t, na_t = _tokens(lines, line, ["nz", "nr", "na"])
    nz = _int(lines, line, f"{label}tallies.nz", nz_t)
    nr = _int(lines, line, f"{label}tallies.nr", nr_t)
    na = _int(lines, line, f"{label}tallies.na", na_t)

    line = lines.take("the number of layers")
    num_layers = _int(lines, line, f"{label}number of layers", _tokens(lines, line, ["number of layers"])[0])

    line = lines.take("n of the medium above")
    n_above = _float(lines, line, f"{label}n_above", _tokens(lines, line, ["n above"])[0], **_N)

    layers = []
    for i in range(num_layers):
        line = lines.take(f"layer {i + 1} of {num_layers}: n mua mus g d")
        tokens = _tokens(lines, line, ["n", "mua [1/cm]", "mus [1/cm]", "g", "d [cm]"])
        field = f"{label}layers[{i}]."
        layers.append((
            _float(lines, line, field + "n", tokens[0], **_N),
            _float(lines, line, field + "mua", tokens[1], **_MU),
            _float(lines, line, field + "mus", tokens[2], **_MU),
            _float(lines, line, field + "g", tokens[3], **_G),
            _float(lines, line, field + "thickness", tokens[4], **_LENGTH, allow_inf=i == num_layers - 1),
        ))

    line = lines.take("n of the medium below")
    n_below = _float(lines, line, f"{label}n_below", _tokens(lines, line, ["n below"])[0], **_N)
    return InParm(output, fmt.upper(), photons, dz, dr, nz, nr, na, n_above, n_below, tuple(layers), first)


def inparm_to_run(inparm: InParm, *, path: str, label: str) -> Run:
    """Build the Run for one InParm block; constructor errors are prefixed with file:line."""
    n, mua, mus, g, d = (list(column) for column in zip(*inparm.layers))
    try:
        tissue = LayeredTissue(n=n, mua=mua, mus=mus, g=g, thickness=d,
                               n_above=inparm.n_above, n_below=inparm.n_below)
        tallies = TallySpec(names=TALLY_NAMES, dz=inparm.dz, dr=inparm.dr,
                            nz=inparm.nz, nr=inparm.nr, na=inparm.na)
        return Run(
            name=Path(inparm.output).stem or inparm.output,
            scene=Scene(tissue=tissue, source=PencilBeam()),
            photons=inparm.photons,
            tallies=tallies,
            options=TraceOptions(),
            seed=None,
            source_file=path,
            mco_output=inparm.output,
            mco_format=inparm.format,
        )
    except (ValueError, TypeError) as err:
        raise ValueError(f"{path}:{inparm.line}: {label}{err}") from None


def read_mci(path) -> list[Run]:
    """Read every run of an MCML input file (.mci).

    MCML tallies all of its arrays, so each Run asks for every tally in `TALLY_NAMES` on the file's
    grid; the source is MCML's normal pencil beam at the origin and `seed` is None (MCML seeds from
    the clock). Raises `ValueError` naming file, line, field, value and allowed range for any
    malformed or physically invalid entry, before anything is simulated.
    """
    name = str(path)
    lines = _DataLines(name, _read_text(path))

    line = lines.take("the file version (1.0)")
    version = _tokens(lines, line, ["file version"])[0]
    if not _FLOAT.fullmatch(version) or float(version) != 1.0:
        raise lines.error(line, f"file version = {version!r} is not supported; allowed 1.0")

    line = lines.take("the number of runs")
    num_runs = _int(lines, line, "number of runs", _tokens(lines, line, ["number of runs"])[0])

    runs, outputs = [], {}
    for k in range(num_runs):
        label = f"run {k + 1}: " if num_runs > 1 else ""
        inparm = read_inparm(lines, label)
        if inparm.output in outputs:
            raise ValueError(
                f"{name}:{inparm.line}: {label}output file name {inparm.output!r} is already used by the "
                f"run at line {outputs[inparm.output]}; each run needs its own output file"
            )
        outputs[inparm.output] = inparm.line
        runs.append(inparm_to_run(inparm, path=name, label=label))

    extra = lines.peek()
    if extra is not None:
        raise lines.error(
            extra, f"unexpected data {' '.join(extra.tokens)!r} after the last of {num_runs} run(s)"
        )
    return runs


def _read_text(path) -> str:
    try:
        return Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not a text file ({err.reason} at byte {err.start})") from None
