"""Summary plots of a run record (matplotlib, headless)."""

from __future__ import annotations

import numpy as np

from .._atomic import atomic_writer


def write_profile_plot(path, record: dict) -> None:
    """Plot the radial reflectance rd_r [1/cm^2] and the depth absorption a_z [1/cm] of a run record
    (`result_to_dict`) into a PNG at `path`, atomically. Panels for tallies the run lacks are omitted."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [k for k in ("rd_r", "a_z", "tt_r") if k in record]
    if not panels:
        raise ValueError("plot: the run has none of the tallies rd_r, a_z, tt_r to plot")
    labels = {
        "rd_r": ("r_cm", "radius r [cm]", "Rd(r) [1/cm²]"),
        "tt_r": ("r_cm", "radius r [cm]", "Tt(r) [1/cm²]"),
        "a_z": ("z_cm", "depth z [cm]", "A(z) [1/cm]"),
    }
    fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 3.6), squeeze=False)
    for ax, name in zip(axes[0], panels):
        axis, xlabel, ylabel = labels[name]
        x = np.asarray(record[name][axis], dtype=float)
        y = np.asarray([np.nan if v is None else v for v in record[name]["value"]], dtype=float)
        # The last bin collects everything beyond the grid (MCML's convention): not a density.
        x, y = x[:-1], y[:-1]
        ax.semilogy(x, np.where(y > 0, y, np.nan), ".-", ms=3)
        err = record[name].get("stderr")
        if err is not None:
            e = np.asarray([np.nan if v is None else v for v in err], dtype=float)[:-1]
            lower = np.where(y - 2 * e > 0, y - 2 * e, np.nan)  # a log axis cannot show <= 0
            ax.fill_between(x, lower, y + 2 * e, alpha=0.3, lw=0, label="±2 s.e.")
            ax.legend(fontsize=8)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    fig.suptitle(f"{record['name']}: rd = {record['rd']:.5g}, a = {record['a']:.5g}, tt = {record['tt']:.5g} "
                 f"({record['photons']:,} photons)", fontsize=9)
    _save(fig, path)


def _values(entries) -> np.ndarray:
    return np.asarray([np.nan if v is None else v for v in entries], dtype=float)


def write_spectrum_plot(path, record: dict) -> None:
    """Plot a spectral run record (`spectral_result_to_dict`) into a PNG at `path`, atomically:
    diffuse reflectance rd per band [-] and the escaping fluorescence rd_fluor (top) and tt_fluor
    (bottom, when any) per band [-], against the band centre [nm], with ±2 standard errors."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if record.get("kind") != "spectral":
        raise ValueError("plot: not a spectral run record (its 'kind' is not 'spectral')")
    wl = np.asarray(record["bands"]["wavelength_nm"], dtype=float)
    fig, (left, right) = plt.subplots(1, 2, figsize=(9.5, 3.6))
    panels = [(left, [("rd", "Rd (all light)")], "diffuse reflectance per band [-]"),
              (right, [("rd_fluor", "escaping top"), ("tt_fluor", "escaping bottom")], "fluorescence per band [-]")]
    for ax, series, ylabel in panels:
        for key, label in series:
            y, e = _values(record[key]), _values(record[f"{key}_stderr"])
            if key == "tt_fluor" and not np.any(y > 0):
                continue
            ax.errorbar(wl, y, yerr=2 * e, fmt=".-", ms=4, capsize=2, label=f"{label} (±2 s.e.)")
        ax.set_xlabel("band centre [nm]")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(
        f"{record['name']}: rd = {record['rd_total']:.5g}, "
        f"fluorescence escaping = {record['rd_fluor_total']:.3g} (top), "
        f"a = {record['a_total']:.5g} ({record['photons']:,} photons, {record['mode']})", fontsize=9)
    _save(fig, path)


def _save(fig, path) -> None:
    """Lay out, write as PNG atomically (a temp file renamed into place), close the figure."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    try:
        with atomic_writer(path, binary=True) as handle:
            fig.savefig(handle, format="png", dpi=120)
    finally:
        plt.close(fig)
