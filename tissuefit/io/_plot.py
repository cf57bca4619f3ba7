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
    fig.tight_layout()
    try:
        with atomic_writer(path, binary=True) as handle:
            fig.savefig(handle, format="png", dpi=120)
    finally:
        plt.close(fig)
