"""`tissuefit.fit`: the U-statistics of a linearisation are unbiased where plain products are not;
a synthetic measurement rendered at hidden parameters (another key, more photons, Gaussian noise)
is fitted back from a wrong guess within the reported uncertainties, with fresh random numbers at
every re-trace; transforms round-trip; bad inputs are refused with messages naming what is wrong."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tissuefit as tf
import tissuefit.fit as tissuefit_fit
from tissuefit import render as rd
from tissuefit.fit import (
    FitConfig,
    FitParameter,
    Measurement,
    linearise,
    parameters_from_names,
    scene_parameters,
)
from tissuefit.io import write_fit_plot, write_fit_report

K = 3.0  # standard errors (two parameters, uncertainties themselves estimated from few renders)
BANDS = tf.BandGrid([450.0, 640.0], 16.0)
ENDO = rd.Endoscope(beta_deg=0.0, fov_deg=20.0, width=8, height=8, distance=1.0)
OPTIONS = rd.RenderOptions(specular_deg=0.0)
LIGHT = rd.Floodlight(0.1)


def tissue(mua, mus=80.0, g=0.85):
    optics = tf.LayerOptics([tf.ConstantAbsorption(jnp.asarray(mua, jnp.float64))], tf.ConstantScattering(mus, g))
    return tf.SpectralTissue([optics], n=[1.4], thickness=[math.inf], bands=BANDS)


MUA = FitParameter("mua", lambda t: t.layers[0].absorbers[0].mua, "log", units="1/cm")


def _measurement(truth, photons, endo=ENDO, seed=0):
    clean = rd.render(tissue(truth), endo, photons=photons, key=jax.random.key(99), illumination=LIGHT,
                      options=rd.RenderOptions(specular_deg=0.0, smoothing="none")).stack
    variance = (0.02 * clean) ** 2 + (0.01 * clean.max()) ** 2
    measured = clean + np.random.default_rng(seed).normal(size=clean.shape) * np.sqrt(variance)
    return Measurement(measured, variance, wavelengths=BANDS.wavelengths)


@pytest.mark.slow  # ~2 min on the shared 2-core machine: over the default suite's budget
def test_recovers_absorption_within_the_reported_uncertainty(tmp_path):
    truth = np.array([2.0, 1.0])
    measured = _measurement(truth, 200_000)
    got = tf.fit(measured, tissue([3.0, 0.6]), [MUA], endoscope=ENDO, key=jax.random.key(1), options=OPTIONS,
                 illumination=LIGHT, config=FitConfig(photons=20_000, max_retraces=10))
    assert got.outcome.successful, got.outcome.value
    # the measurement is itself a render: its Monte Carlo noise is the fit's simulation part scaled by
    # sqrt(photons ratio x averaged) (the noise of a render falls as 1 / sqrt(photons))
    one = got.simulation_uncertainties * math.sqrt(got.settings["averaged"])
    spread = np.hypot(got.uncertainties, one * math.sqrt(20_000 / 200_000))
    assert np.all(np.abs(got.values - truth) <= K * spread), (got.values, spread)
    assert np.all(got.uncertainties < 0.1 * truth)  # a fit that says something
    assert got.residuals.shape == measured.shape and np.all(np.isfinite(got.residuals))
    assert abs(got.correlation[0, 1]) <= 1 + 1e-9 and got.correlation[0, 0] == pytest.approx(1.0)
    write_fit_report(got, tmp_path / "fit.json")
    write_fit_plot(got, tmp_path / "fit.png")
    report = json.loads((tmp_path / "fit.json").read_text())
    assert [p["name"] for p in report["parameters"]] == ["mua[0]", "mua[1]"]
    assert report["converged"] and len(report["history"]) == len(got.history)
    assert report["method"] == tissuefit_fit.METHOD
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
    data = Measurement(np.ones((2, 8, 8)), 1.0)
    call = dict(endoscope=ENDO, options=OPTIONS, illumination=LIGHT, config=FitConfig(photons=100))
    with pytest.raises(ValueError, match="no parameters"):
        tf.fit(data, t, [], **call)
    with pytest.raises(ValueError, match="3 bands, the tissue's band grid 2"):
        tf.fit(Measurement(np.ones((3, 8, 8)), 1.0), t, [MUA], **call)
    with pytest.raises(ValueError, match="4 x 8 pixels, the endoscope's 8 x 8"):
        tf.fit(Measurement(np.ones((2, 4, 8)), 1.0), t, [MUA], **call)
    with pytest.raises(TypeError, match="give a tissuefit.fit.Measurement"):
        tf.fit(np.ones((2, 8, 8)), t, [MUA], **call)
    with pytest.raises(ValueError, match="all masked"):
        Measurement(np.ones((2, 8, 8)), 1.0, mask=np.zeros((2, 8, 8), bool))
    with pytest.raises(ValueError, match="negative"):
        Measurement(np.ones((2, 8, 8)), -1.0)
    with pytest.raises(ValueError, match="outside its bounds"):
        tf.fit(data, t, [FitParameter("mua", MUA.where, "log", (2.5, 10.0))], **call)
    with pytest.raises(ValueError, match="names repeat"):
        tf.fit(data, t, [MUA, MUA], **call)
    with pytest.raises(ValueError, match="transform = 'sqrt'"):
        FitParameter("x", MUA.where, "sqrt")
    with pytest.raises(ValueError, match="fit.batches = 2; allowed 4"):
        FitConfig(batches=2)
    with pytest.raises(ValueError, match="fit.average = 0"):
        FitConfig(average=0)


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


def test_batch_u_statistics_are_unbiased_and_the_jackknife_covers_the_step():
    """Synthetic batches with known means: the plain J^T J and J^T r of the batch means are biased by
    each batch's noise times itself; the U-statistics over pairs of batches are not (their mean over
    many draws equals E[J]^T E[J] and E[J]^T (E[s] - m) within its error), and the jackknife
    covariances of the step and of the gradient predict their spread."""
    rng = np.random.default_rng(4)
    n, p, batches, draws = 40, 2, 8, 600
    jac = rng.normal(size=(n, p))
    truth_s = rng.uniform(1.0, 2.0, n)
    data = truth_s + jac @ np.array([0.3, -0.2])  # the optimum sits 0.3, -0.2 away in x
    variance, band = np.ones(n), np.zeros(n, int)
    h_u, h_plain, g_u, steps, covs, g_covs = [], [], [], [], [], []
    for _ in range(draws):
        # correlated noise of a batch's image and its derivative, as one photon's contribution gives
        e = rng.normal(size=(batches, n, 1)) * 0.5
        s_b = truth_s + e[..., 0] + 0.3 * rng.normal(size=(batches, n))
        j_b = jac + e * np.array([1.0, -0.5]) + 0.5 * rng.normal(size=(batches, n, p))
        lin = linearise(np.zeros(p), s_b, j_b, data, variance, band, simulation_variance=False)
        h_u.append(lin.hessian), h_plain.append(lin.hessian + lin.noise), g_u.append(lin.gradient)
        steps.append(lin.step), covs.append(lin.step_covariance), g_covs.append(lin.gradient_covariance)
    want_h, want_g = jac.T @ jac, jac.T @ (truth_s - data)
    se_h = np.std(h_u, axis=0) / math.sqrt(draws)
    assert np.all(np.abs(np.mean(h_u, axis=0) - want_h) < 4 * se_h)
    # the bias the U-statistic removes: each batch's noise squared adds to the plain diagonal
    assert np.all(np.diag(np.mean(h_plain, axis=0) - want_h) > 10 * np.diag(se_h))
    se_g = np.std(g_u, axis=0) / math.sqrt(draws)
    assert np.all(np.abs(np.mean(g_u, axis=0) - want_g) < 4 * se_g)
    # the jackknife covariance against the steps' empirical spread: an empirical variance of `draws`
    # steps has a relative standard error sqrt(2 / (draws - 1)); the jackknife may err on the safe
    # side (Efron & Stein 1981: its expectation is at least the variance), never below it
    ratio = np.diag(np.mean(covs, axis=0)) / np.diag(np.cov(np.asarray(steps).T))
    se = math.sqrt(2 / (draws - 1))
    assert np.all(ratio > 1 - 4 * se) and np.all(ratio < 1 + 0.3), ratio
    # the gradient is a degree-2 U-statistic (products of two batches' noise): its jackknife carries
    # the second-order term's variance on top (Efron & Stein 1981), 1.33x and 0.98x here at this
    # noise level (0.5 on J and s per batch); safe side only, within a factor 1.5
    ratio = np.diag(np.mean(g_covs, axis=0)) / np.diag(np.cov(np.asarray(g_u).T))
    assert np.all(ratio > 1 - 4 * se) and np.all(ratio < 1.5), ratio


def test_re_traces_draw_fresh_random_numbers_and_average_the_settled_landings():
    """A tiny fit (6 x 6, two bands, 4000 photons a re-trace): every re-trace renders with its own
    random numbers, settled landing points are averaged, and the result lands within its uncertainty
    of a measurement rendered without noise of its own beyond the Monte Carlo."""
    endo = rd.Endoscope(beta_deg=0.0, fov_deg=20.0, width=6, height=6, distance=1.0)
    truth = np.array([2.0, 1.0])
    clean = rd.render(tissue(truth), endo, photons=40_000, key=jax.random.key(99), illumination=LIGHT,
                      options=rd.RenderOptions(specular_deg=0.0, smoothing="none")).stack
    measured = Measurement(clean, (0.01 * clean.max()) ** 2)
    seen = []
    got = tf.fit(measured, tissue([2.6, 0.8]), [MUA], endoscope=endo, key=jax.random.key(1), options=OPTIONS,
                 illumination=LIGHT, config=FitConfig(photons=4_000, max_retraces=10, average=2, batches=8),
                 progress=seen.append)
    assert got.outcome.successful, got.outcome.value
    assert got.settings["averaged"] == 2 and seen[-1].samples == 2 and len(seen) == len(got.history) <= 10
    assert [r.retrace for r in seen] == list(range(len(seen)))
    assert all(0 < r.seconds_render <= r.seconds for r in seen)  # the render's stages, counted once
    assert seen[0].phase in ("approach", "arrive") and seen[-1].phase == "sample"
    one = got.simulation_uncertainties * math.sqrt(2)  # one render's; the measurement has 10x the photons
    spread = np.hypot(got.uncertainties, one / math.sqrt(10))
    assert np.all(np.abs(got.values - truth) <= K * spread), (got.values, spread)
    with pytest.raises(tf.OutcomeError, match="did not settle"):
        tf.fit(measured, tissue([2.6, 0.8]), [MUA], endoscope=endo, key=jax.random.key(1), options=OPTIONS,
               illumination=LIGHT, config=FitConfig(photons=1_000, max_retraces=1))
    unsettled = tf.fit(measured, tissue([2.6, 0.8]), [MUA], endoscope=endo, key=jax.random.key(1), options=OPTIONS,
                       illumination=LIGHT, config=FitConfig(photons=1_000, max_retraces=1), throw=False)
    assert unsettled.outcome is tf.Outcome.NOT_CONVERGED and not unsettled.outcome.successful


def test_the_report_says_what_ran_and_where_the_estimate_comes_from():
    """Issue 25, item 6 (fit.json's "solver" said levenberg-marquardt when Gauss-Newton steps ran): the
    report's "ran" counts the re-traces per phase and says whether the estimate is an average of
    settled landing points or, for a fit that stopped early, the last trace point."""
    from types import SimpleNamespace

    from tissuefit.io._fitreport import fit_ran

    def record(phase, photons):
        return SimpleNamespace(phase=phase, photons=photons)

    history = [record("approach", 25_000)] * 2 + [record("arrive", 100_000)] + [record("sample", 100_000)] * 4
    done = SimpleNamespace(history=history, outcome=tf.Outcome.SUCCESSFUL, settings={"averaged": 4, "average": 4})
    assert fit_ran(done) == {"retraces": 7, "retraces_by_phase": {"approach": 2, "arrive": 1, "sample": 4},
                             "photons_by_phase": {"approach": 25_000, "arrive": 100_000, "sample": 100_000},
                             "steps": "Gauss-Newton", "estimate": "the mean of 4 settled landing points"}
    early = SimpleNamespace(history=history[:3], outcome=tf.Outcome.NOT_CONVERGED, settings={"averaged": 0, "average": 4})
    assert fit_ran(early)["estimate"] == ("the last trace point (not converged: 0 of the 4 settled landing "
                                          "points to average)")
