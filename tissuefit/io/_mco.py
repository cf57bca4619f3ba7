"""MCML's ASCII output format (.mco): writer and reader.

The writer follows the layout of MCML 1.2's `WriteResult` (Wang & Jacques 1992): a version line
("A1"), a comment header, the echo of the input parameters ("InParm"), then the sections RAT, A_l,
A_z, Rd_r, Rd_a, Tt_r, Tt_a (one number per line) and A_rz, Rd_ra, Tt_ra (row-major [r][z] or
[r][angle], five numbers per line). Our own additions (tissuefit version, seed, standard errors)
are `#` comment lines, which MCML-style readers skip.
"""

from __future__ import annotations

import re

import numpy as np

from .._atomic import write_text_atomic
from .._outcome import Outcome
from ..scene import PencilBeam
from ..transport import TraceResult
from ._mci import _FLOAT, _DataLines, _read_text, read_inparm
from ._report import tissuefit_version
from ._run import Run

_ARRAYS = ("a_layer", "a_z", "rd_r", "rd_a", "tt_r", "tt_a", "a_rz", "rd_ra", "tt_ra")
_NUMBER = re.compile(_FLOAT.pattern + r"|[+-]?(inf(inity)?|nan)", re.IGNORECASE)

# Section keyword, our tally name, header comment (MCML's wording), shape from InParm.
_SECTIONS_1D = (
    ("A_l", "a_layer", "A_l #Absorption as a function of layer. [-]"),
    ("A_z", "a_z", "A_z #A[0], [1],..A[nz-1]. [1/cm]"),
    ("Rd_r", "rd_r", "Rd_r #Rd[0], [1],..Rd[nr-1]. [1/cm2]"),
    ("Rd_a", "rd_a", "Rd_a #Rd[0], [1],..Rd[na-1]. [sr-1]"),
    ("Tt_r", "tt_r", "Tt_r #Tt[0], [1],..Tt[nr-1]. [1/cm2]"),
    ("Tt_a", "tt_a", "Tt_a #Tt[0], [1],..Tt[na-1]. [sr-1]"),
)
_SECTIONS_2D = (
    ("A_rz", "a_rz", "A", "z", "[1/cm3]"),
    ("Rd_ra", "rd_ra", "Rd", "angle", "[1/(cm2sr)]."),
    ("Tt_ra", "tt_ra", "Tt", "angle", "[1/(cm2sr)]."),
)


def format_mco(run: Run, result: TraceResult, *, seed: int, seconds: float) -> str:
    """The text of an MCML ASCII output file for `run` and its `result` (see `write_mco`)."""
    missing = [name for name in _ARRAYS if getattr(result, name) is None]
    if missing:
        raise ValueError(
            f"write_mco: the result lacks the tallies {missing}; an .mco file holds all of MCML's "
            "arrays, so trace with TallySpec(names=TALLY_NAMES)"
        )
    tissue = run.scene.tissue
    spec = result.tallies
    arrays = {name: np.asarray(getattr(result, name), dtype=np.float64) for name in _ARRAYS}
    out: list[str] = []
    put = out.append

    put("A1 \t# Version number of the file format.\n\n")
    put("####\n# Data categories include: \n# InParm, RAT, \n")
    put("# A_l, A_z, Rd_r, Rd_a, Tt_r, Tt_a, \n# A_rz, Rd_ra, Tt_ra \n####\n\n")
    put(f"# User time: {seconds:8.0f} sec = {seconds / 3600:8.2f} hr.   Simulation time of this run.\n")
    put(f"# Written by tissuefit {tissuefit_version()}: run {run.name!r} from {run.source_file}, seed {seed}, "
        f"{seconds:.3f} s wall time (compilation included).\n")
    put(f"# Standard errors: Rd {float(result.rd_stderr):.6G}, "
        f"A {float(result.a_stderr):.6G}, Tt {float(result.tt_stderr):.6G}.\n")
    if not _is_mcml_beam(run.scene.source):
        put(f"# Source: {type(run.scene.source).__name__} (not MCML's normal pencil beam).\n")
    if result.outcome is Outcome.BUDGET_EXHAUSTED:
        put("# WARNING: the step budget was exhausted; the tallies are incomplete.\n")
    put("\n")

    put("InParm \t\t\t# Input parameters. cm is used.\n")
    put(f"{run.mco_output or run.name + '.mco'} \t{run.mco_format or 'A'}\t\t# output file name, ASCII.\n")
    put(f"{result.photons} \t\t\t# No. of photons\n")
    put(f"{spec.dz:G}\t{spec.dr:G}\t\t# dz, dr [cm]\n")
    put(f"{spec.nz}\t{spec.nr}\t{spec.na}\t# No. of dz, dr, da.\n\n")
    put(f"{tissue.num_layers}\t\t\t\t\t# Number of layers\n")
    put("#n\tmua\tmus\tg\td\t# One line for each layer\n")
    put(f"{float(tissue.n_above):G}\t\t\t\t\t# n for medium above\n")
    columns = [np.asarray(c, dtype=np.float64) for c in (tissue.n, tissue.mua, tissue.mus, tissue.g, tissue.thickness)]
    for i, layer in enumerate(zip(*columns), start=1):
        put("\t".join(f"{v:G}" for v in layer) + f"\t# layer {i}\n")
    put(f"{float(tissue.n_below):G}\t\t\t\t\t# n for medium below\n\n")

    put("RAT #Reflectance, absorption, transmission. \n")
    for value, label in ((result.rsp, "Specular reflectance"), (result.rd, "Diffuse reflectance"),
                         (result.a, "Absorbed fraction"), (result.tt, "Transmittance")):
        put(f"{float(value):<14.6G} \t#{label} [-]\n")
    put("\n")

    for keyword, name, header in _SECTIONS_1D:
        put(header + "\n")
        style = "12.4G" if keyword == "A_l" else "12.4E"
        put("".join(f"{v:{style}}\n" for v in arrays[name].reshape(-1)))
        put("\n")

    for keyword, name, symbol, axis, unit in _SECTIONS_2D:
        put(f"# {symbol}[r][{axis}]. {unit}\n")
        put(f"# {symbol}[0][0], [0][1],..[0][n{axis[0]}-1]\n")
        put(f"# {symbol}[1][0], [1][1],..[1][n{axis[0]}-1]\n# ...\n")
        put(f"# {symbol}[nr-1][0], [nr-1][1],..[nr-1][n{axis[0]}-1]\n{keyword}\n")
        for k, v in enumerate(arrays[name].reshape(-1), start=1):
            put(f"{v:12.4E} ")
            if k % 5 == 0:
                put("\n")
        put("\n")
    return "".join(out)


def _is_mcml_beam(source) -> bool:
    if not isinstance(source, PencilBeam):
        return False
    return all(float(getattr(source, f)) == 0.0 for f in ("x", "y", "polar_deg", "azimuth_deg"))


def write_mco(path, run: Run, result: TraceResult, *, seed: int, seconds: float) -> None:
    """Write `result` of `run` to `path` in MCML's ASCII output format (.mco), atomically.

    Arguments:
    - `run`: the Run traced (its tissue and grid are echoed in the InParm block).
    - `result`: a TraceResult holding every tally in `TALLY_NAMES` (MCML writes all arrays).
    - `seed`: the PRNG seed used, recorded in a comment line.
    - `seconds`: wall time of the run [s], written where MCML writes its user time.

    Units are MCML's: RAT and A_l [-], A_z [1/cm], Rd_r and Tt_r [1/cm^2], Rd_a and Tt_a [1/sr],
    A_rz [1/cm^3], Rd_ra and Tt_ra [1/(cm^2 sr)]. The file is written to a temporary file in the
    same folder and moved into place, so an existing file survives any failure.
    """
    write_text_atomic(path, format_mco(run, result, seed=seed, seconds=seconds))


def read_mco(path) -> dict:
    """Read an MCML ASCII output file (.mco), ours or MCML's own.

    Returns a dict with:
    - `version`: the format tag ("A1"); `user_time_s`: the run time from the header comment
      (None if absent).
    - `inparm`: the echoed input (`output`, `format`, `photons`, `dz`, `dr` [cm], `nz`, `nr`, `na`,
      `n_above`, `n_below`, `layers`: list of {n, mua [1/cm], mus [1/cm], g, thickness [cm]}).
    - `rsp`, `rd`, `a`, `tt`: floats [-].
    - arrays (float64 numpy) named as our tallies: `a_layer` [-] (layers,), `a_z` [1/cm] (nz,),
      `rd_r`, `tt_r` [1/cm^2] (nr,), `rd_a`, `tt_a` [1/sr] (na,), `a_rz` [1/cm^3] (nr, nz),
      `rd_ra`, `tt_ra` [1/(cm^2 sr)] (nr, na).
    Raises `ValueError` with file:line for a malformed file.
    """
    name = str(path)
    text = _read_text(path)
    lines = _DataLines(name, text)

    line = lines.take("the format version (A1)")
    if len(line.tokens) != 1 or line.tokens[0] not in ("A1", "B1"):
        raise lines.error(line, f"format version = {' '.join(line.tokens)!r}; allowed 'A1' (or 'B1')")
    out: dict = {"version": line.tokens[0]}
    timing = re.search(r"^#\s*User time:\s*([0-9.eE+-]+)\s*sec", text, re.MULTILINE)
    out["user_time_s"] = float(timing.group(1)) if timing else None

    _keyword(lines, "InParm")
    inparm = read_inparm(lines, "InParm: ")
    out["inparm"] = inparm.to_dict()

    rat = _numbers(lines, "RAT", 4)
    out.update(rsp=float(rat[0]), rd=float(rat[1]), a=float(rat[2]), tt=float(rat[3]))
    sizes = {"A_l": len(inparm.layers), "A_z": inparm.nz, "Rd_r": inparm.nr, "Rd_a": inparm.na,
             "Tt_r": inparm.nr, "Tt_a": inparm.na}
    for keyword, tally, _ in _SECTIONS_1D:
        out[tally] = _numbers(lines, keyword, sizes[keyword])
    shapes = {"A_rz": (inparm.nr, inparm.nz), "Rd_ra": (inparm.nr, inparm.na), "Tt_ra": (inparm.nr, inparm.na)}
    for keyword, tally, *_ in _SECTIONS_2D:
        shape = shapes[keyword]
        out[tally] = _numbers(lines, keyword, shape[0] * shape[1]).reshape(shape)

    extra = lines.peek()
    if extra is not None:
        raise lines.error(extra, f"unexpected data {' '.join(extra.tokens)!r} after the Tt_ra section")
    return out


def _keyword(lines: _DataLines, keyword: str) -> None:
    line = lines.take(f"the section keyword {keyword!r}")
    if line.tokens != [keyword]:
        raise lines.error(line, f"expected the section keyword {keyword!r}, found {' '.join(line.tokens)!r}")


def _numbers(lines: _DataLines, keyword: str, count: int) -> np.ndarray:
    """The `count` numbers following the line `keyword`."""
    _keyword(lines, keyword)
    values: list[float] = []
    while len(values) < count:
        line = lines.peek()
        if line is None or not _NUMBER.fullmatch(line.tokens[0]):
            message = f"section {keyword}: expected {count} numbers, found {len(values)}"
            if line is None:
                raise ValueError(f"{lines.path}: {message} before the end of the file")
            raise lines.error(line, message)
        lines.take("")
        for token in line.tokens:
            if not _NUMBER.fullmatch(token):
                raise lines.error(line, f"section {keyword}: {token!r} is not a number")
            values.append(float(token))
    if len(values) != count:
        raise lines.error(line, f"section {keyword}: expected {count} numbers, found {len(values)}")
    return np.asarray(values, dtype=np.float64)
