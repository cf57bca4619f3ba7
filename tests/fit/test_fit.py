"""`tissuefit.fit`: a synthetic measurement rendered at hidden parameters (another key, more
photons, Gaussian noise) is fitted back from a wrong guess, within the reported uncertainties;
transforms round-trip; bad inputs are refused with messages naming what is wrong."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tissuefit as tf
from tissuefit import render as rd
from tissuefit.fit import FitParameter, parameters_from_names, scene_parameters, write_fit_plot, write_fit_report

K = 3.0  # standard errors (two parameters, uncertainties themselves estimated from few renders)
BANDS = tf.BandGrid([450.0, 640.0], 16.0)
ENDO = rd.Endoscope(beta_deg=0.0, fov_deg=20.0, width=8, height=8, distance=1.0)
OPTIONS = rd.RenderOptions(specular_deg=0.0, surface_radius=0.02)
LIGHT = rd.Floodlight(0.1)
PHOTONS, MEASURED_PHOTONS = 10_000, 50_000


def tissue(mua, mus=80.0, g=0.85):
    optics = tf.LayerOptics([tf.ConstantAbsorption(jnp.asarray(mua, jnp.float64))], tf.ConstantScattering(mus, g))
    return tf.SpectralTissue([optics], n=[1.4], thickness=[math.inf], bands=BANDS)


MUA = FitParameter("mua", lambda t: t.layers[0].absorbers[0].mua, "log", units="1/cm")


@pytest.mark.slow  # ~100 s on the shared 2-core machine: over the default suite's budget
def test_recovers_absorption_within_the_reported_uncertainty(tmp_path):
    truth = np.array([2.0, 1.0])
    clean = rd.render(tissue(truth), ENDO, photons=MEASURED_PHOTONS, key=jax.random.key(99), options=OPTIONS,
                      illumination=LIGHT).stack
    variance = (0.02 * clean) ** 2 + (0.01 * clean.max()) ** 2
    measured = clean + np.random.default_rng(0).normal(size=clean.shape) * np.sqrt(variance)
    got = tf.fit(measured, tissue([3.0, 0.6]), [MUA], endoscope=ENDO, photons=PHOTONS, key=jax.random.key(1),
                 options=OPTIONS, illumination=LIGHT, variance=variance, max_retraces=8)
    assert got.converged, got.reason
    # the measurement is itself a render: its Monte Carlo noise is the fit's simulation part scaled by
    # sqrt(photons ratio) (the noise of a render falls as 1 / sqrt(photons))
    spread = np.hypot(got.uncertainties, got.simulation_uncertainties * math.sqrt(PHOTONS / MEASURED_PHOTONS))
    assert np.all(np.abs(got.values - truth) <= K * spread), (got.values, spread)
    assert np.all(got.uncertainties < 0.15 * truth)  # a fit that says something
    assert got.residuals.shape == measured.shape and np.all(np.isfinite(got.residuals))
    assert abs(got.correlation[0, 1]) <= 1 + 1e-9 and got.correlation[0, 0] == pytest.approx(1.0)
    write_fit_report(got, tmp_path / "fit.json")
    write_fit_plot(got, tmp_path / "fit.png")
    report = json.loads((tmp_path / "fit.json").read_text())
    assert [p["name"] for p in report["parameters"]] == ["mua[0]", "mua[1]"]
    assert report["converged"] and len(report["history"]) == len(got.history)
    assert len(report["bands"]) == 2 and report["bands"][0]["ssim"] is not None
    assert (tmp_path / "fit.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("transform, bounds, values", [
    ("log", None, [1e-3, 2.0, 400.0]), ("log", (0.5, 50.0), [0.6, 3.0, 49.0]),
    ("logit-g", None, [0.01, 0.85, 0.98]), ("identity", (-1.0, 3.0), [-0.9, 1.3]), ("identity", None, [-5.0, 7.0]),
])
def test_transforms_round_trip(transform, bounds, values):
    p = FitParameter("p", lambda t: t, transform, bounds)
    x = p.to_unconstrained(np.asarray(values))
    np.testing.assert_allclose(np.asarray(p.to_value(jnp.asarray(x))), values, rtol=1e-12)


def test_bad_inputs_are_refused_with_their_reasons():
    t = tissue([2.0, 1.0])
    data = np.ones((2, 8, 8))
    call = dict(endoscope=ENDO, photons=100, options=OPTIONS, illumination=LIGHT, variance=1.0)
    with pytest.raises(ValueError, match="no parameters"):
        tf.fit(data, t, [], **call)
    with pytest.raises(ValueError, match="3 bands, the tissue's band grid 2"):
        tf.fit(np.ones((3, 8, 8)), t, [MUA], **call)
    with pytest.raises(ValueError, match="4 x 8 pixels, the endoscope's 8 x 8"):
        tf.fit(np.ones((2, 4, 8)), t, [MUA], **call)
    with pytest.raises(ValueError, match="no noise model"):
        tf.fit(data, t, [MUA], **{**call, "variance": None})
    with pytest.raises(ValueError, match="solver = 'newton'"):
        tf.fit(data, t, [MUA], solver="newton", **call)
    with pytest.raises(ValueError, match="approach = 'walk'; allowed one of 'solve', 'gauss-newton'"):
        tf.fit(data, t, [MUA], approach="walk", **call)
    with pytest.raises(ValueError, match="approach_photons = 0; allowed an integer >= 1"):
        tf.fit(data, t, [MUA], approach_photons=0, **call)
    with pytest.raises(ValueError, match="all masked"):
        tf.fit(data, t, [MUA], mask=np.zeros((2, 8, 8), bool), **call)
    with pytest.raises(ValueError, match="outside its bounds"):
        tf.fit(data, t, [FitParameter("mua", MUA.where, "log", (2.5, 10.0))], **call)
    with pytest.raises(ValueError, match="names repeat"):
        tf.fit(data, t, [MUA, MUA], **call)
    with pytest.raises(ValueError, match="transform = 'sqrt'"):
        FitParameter("x", MUA.where, "sqrt")


def test_scene_parameter_names_and_their_errors():
    optics = tf.LayerOptics([tf.ConstantAbsorption(2.0), tf.protoporphyrin_ix(BANDS)], tf.PowerLawScattering(18.9, 1.3, 0.9))
    region = tf.Sphere(center=[0.0, 0.0, 0.05], radius=0.05, layer=0,
                       optics=tf.LayerOptics([tf.ConstantAbsorption(1.0)], tf.ConstantScattering(50.0, 0.8)))
    t = tf.SpectralTissue([optics], n=[1.4], thickness=[math.inf], bands=BANDS, regions=[region])
    names = set(scene_parameters(t))
    assert {"layer0.mua", "layer0.c_ppix", "layer0.yield_ppix", "layer0.a", "layer0.b", "layer0.g",
            "region0.mua", "region0.mus", "region0.g"} <= names
    (c,) = parameters_from_names(t, ["c_ppix"])
    assert c.name == "layer0.c_ppix" and float(c.where(t)) == pytest.approx(0.33)
    assert parameters_from_names(t, ["a"])[0].name == "layer0.a"
    with pytest.raises(ValueError, match="ambiguous: it names layer0.mua, region0.mua"):
        parameters_from_names(t, ["mua"])
    with pytest.raises(ValueError, match="not a parameter of this scene; available: layer0.mua, "):
        parameters_from_names(t, ["mus_prime"])


def test_the_averaged_solves_scatter_is_compared_with_one_renders_covariance():
    """`_sample_spread`: chi^2 of the settled solves about their mean against one render's simulation
    covariance, with parameters x (solves - 1) degrees of freedom; it follows chi^2 when the
    covariance is right (here: draws from it)."""
    from tissuefit.fit._fit import _sample_spread
    from tissuefit.fit._parameters import Layout

    layout = Layout((MUA,), ((2,),))
    cov = np.array([[0.04, 0.01], [0.01, 0.09]])  # parameter units (1/cm)^2
    rng = np.random.default_rng(3)
    chi2, dof = 0.0, 0
    for _ in range(200):
        draws = rng.multivariate_normal([2.0, 1.0], cov, size=4)
        got = _sample_spread([np.log(d) for d in draws], layout, cov)
        chi2, dof = chi2 + got["chi2"], dof + got["dof"]
        np.testing.assert_allclose(got["values"], draws, rtol=1e-12)
    assert dof == 200 * 2 * 3
    assert abs(chi2 / dof - 1.0) < 4 * math.sqrt(2 / dof)  # chi^2 / dof within 4 of its standard errors
    assert _sample_spread([np.zeros(2)], layout, cov) is None  # one solve: no spread


def test_re_traces_draw_fresh_random_numbers_and_average_the_settled_solves():
    """A tiny fit (6 x 6, two bands, 3000 photons): every re-trace renders with its own random
    numbers, the settled solves are averaged, and the result lands within its uncertainty of a
    measurement rendered without noise of its own beyond the Monte Carlo."""
    endo = rd.Endoscope(beta_deg=0.0, fov_deg=20.0, width=6, height=6, distance=1.0)
    truth = np.array([2.0, 1.0])
    clean = rd.render(tissue(truth), endo, photons=30_000, key=jax.random.key(99), options=OPTIONS,
                      illumination=LIGHT).stack
    variance = (0.01 * clean.max()) ** 2 * np.ones_like(clean)
    seen = []
    got = tf.fit(clean, tissue([2.6, 0.8]), [MUA], endoscope=endo, photons=3_000, key=jax.random.key(1),
                 options=OPTIONS, illumination=LIGHT, variance=variance, max_retraces=8, average=2,
                 progress=seen.append)
    assert got.converged, got.reason
    assert got.settings["averaged_solves"] == 2 and got.settings["sample_spread"]["dof"] == 2
    assert [h["samples"] for h in seen][-1] == 2 and len(seen) == len(got.history) <= 8
    # the steps' J^T J - D is the mean over every render after the approach (one more each re-trace)
    counts = [h["curvature_renders"] for h in seen]
    assert counts[0] == 0 and counts[-1] >= 2 + 1  # the burn-in step and the two estimates
    assert all(b - a in (0, 1) for a, b in zip(counts, counts[1:])) and counts[-1] == len(seen) - counts.count(0)
    one = got.simulation_uncertainties * math.sqrt(2)  # one render's; the measurement has 10x the photons
    spread = np.hypot(got.uncertainties, one / math.sqrt(10))
    assert np.all(np.abs(got.values - truth) <= K * spread), (got.values, spread)
    with pytest.raises(ValueError, match="average = 0; allowed an integer 1..100"):
        tf.fit(clean, tissue(truth), [MUA], endoscope=endo, photons=100, options=OPTIONS, illumination=LIGHT,
               variance=variance, average=0)


def test_the_noise_hessian_is_each_records_derivative_times_itself():
    """`_noise_hessian` (the squared-kernel pullback `RenderReplay.noise_weights` and one Jacobian of
    the records' powers) against the brute-force sum over records i of J_i^T J_i, J_i the derivative
    of record i's own part of the whitened image; and weighted by the residuals squared (D_r)."""
    from tissuefit.fit._fit import _noise_hessian
    from tissuefit.fit._parameters import Layout
    from tissuefit.render._render import _surface_image

    endo = rd.Endoscope(beta_deg=0.0, fov_deg=20.0, width=4, height=4, distance=1.0)
    t = tissue([2.0, 1.0])
    out = rd.render(t, endo, photons=250, key=jax.random.key(5), options=OPTIONS, illumination=LIGHT, replay=True)
    replay, layout = out.replay, Layout((MUA,), ((2,),))
    x = jnp.log(jnp.asarray([2.0, 1.0]))
    rng = np.random.default_rng(2)
    sigma = jnp.asarray(rng.uniform(0.5, 2.0, out.stack.shape) * out.stack.mean())
    use = rng.uniform(size=out.stack.shape) > 0.2
    r_map = rng.normal(size=out.stack.shape)
    n = int(replay.surface.records.count)
    assert n > 20

    def own(i, xv):  # record i's part of the whitened image [bands, H, W]
        p = replay.surface.power(layout.tissue(t, xv))
        one = jnp.where(jnp.arange(p.shape[0]) == i, 1.0, 0.0)[:, None]
        return jnp.where(use, _surface_image(replay, p * one) / sigma, 0.0)

    j = np.asarray(jax.vmap(lambda i: jax.jacfwd(lambda xv: own(i, xv))(x))(jnp.arange(n)))  # [n, b, H, W, p]
    want = np.einsum("ibhwp,ibhwq->pq", j, j)
    want_r = np.einsum("ibhwp,bhw,ibhwq->pq", j, r_map**2, j)
    got, got_r = _noise_hessian(layout, t, replay, x, sigma, use, r_map)
    np.testing.assert_allclose(got, want, rtol=1e-4)
    np.testing.assert_allclose(got_r, want_r, rtol=1e-4)
    assert _noise_hessian(layout, t, replay, x, sigma, use)[1] is None
