"""Image gradients of photon-map renders (`replayed_render` -> `RenderReplay`): the replayed stack is the render,
selected pixels' derivatives match finite differences of independent renders, modes agree, and
pixels no photon reached stay finite."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tissuefit as tf
from tissuefit import render as rd
from tissuefit.replay import replayed_render

K = 4.0  # standard errors (two bands x two parameters, standard errors from few renders)
BANDS = tf.BandGrid([450.0, 640.0], 16.0)
ENDO = rd.Endoscope(beta_deg=15.0, fov_deg=16.0, width=8, height=8, distance=1.0)
OPTIONS = rd.RenderOptions(specular_deg=2.0, surface_radius=0.04, volume_radius=0.04, estimator="photon-map")


def tissue(p):
    mua, mus = p
    optics = tf.LayerOptics([tf.ConstantAbsorption(jnp.stack([mua, 0.5 * mua]))], tf.ConstantScattering(jnp.stack([mus, 0.8 * mus]), 0.85))
    return tf.SpectralTissue([optics], n=[1.4], thickness=[math.inf], bands=BANDS)


P0 = jnp.asarray([2.0, 80.0])
BLOCK = (slice(None), slice(2, 6), slice(2, 6))  # the central 4 x 4 pixels of each band


def block(stack):
    return stack[BLOCK].mean((1, 2))


def render(p, seed):
    return rd.render(tissue(p), ENDO, photons=20_000, key=jax.random.key(seed), options=OPTIONS,
                     illumination=rd.Floodlight(0.6))


def replayed(p, seed):
    """(result, replay) of the render at p."""
    return replayed_render(tissue(p), ENDO, photons=20_000, key=jax.random.key(seed), options=OPTIONS,
                           illumination=rd.Floodlight(0.6))


def test_replayed_stack_is_the_render_and_modes_agree():
    got, rep = replayed(P0, 0)
    np.testing.assert_allclose(np.asarray(rep.stack(tissue(P0))), got.stack, rtol=1e-6, atol=1e-9 * got.stack.max())
    f = lambda p: block(rep.stack(tissue(p)))  # noqa: E731
    jf, jr = np.asarray(jax.jacfwd(f)(P0)), np.asarray(jax.jacrev(f)(P0))
    np.testing.assert_allclose(jf, jr, rtol=1e-6, atol=1e-14)  # float32 maps
    assert jf[0, 0] < 0 and jf[1, 0] < 0  # more absorption, darker in both bands
    ess = rep.effective_sample_size(tissue(P0 * 1.1))
    assert 0 < float(ess["surface"][0]) < 1


def test_re_traces_share_the_replay_structure():
    """A fit's re-traces (nearby parameters, other keys: other record counts and extents) give
    replays of one static structure (padded buffers, rounded maps), so the replay and the inner
    solve compile once (a count that crosses a buffer size recompiles once more)."""
    import dataclasses

    import equinox as eqx

    options = dataclasses.replace(OPTIONS, step_length=0.01)  # as `fit` fixes it after its first render
    (a, ra), (b, rb) = (replayed_render(tissue(p), ENDO, photons=20_000, key=jax.random.key(s), options=options,
                                        illumination=rd.Floodlight(0.6)) for p, s in ((P0, 0), (P0 * jnp.asarray([1.05, 0.97]), 1)))
    assert a.maps.surface_photons != b.maps.surface_photons
    static = [eqx.partition(r, eqx.is_array)[1] for r in (ra, rb)]
    assert eqx.tree_equal(*static)
    assert jax.tree.structure(ra) == jax.tree.structure(rb)
    assert [np.shape(x) for x in jax.tree.leaves(ra)] == [np.shape(x) for x in jax.tree.leaves(rb)]


@pytest.mark.slow  # 12 renders, ~100 s on 2 cores
def test_pixel_gradients_match_finite_differences_of_independent_renders():
    rows = []
    for s in range(4):
        rep = replayed(P0, s)[1]
        rows.append(np.asarray(jax.jacfwd(lambda p: block(rep.stack(tissue(p))))(P0)))  # [bands, 2]
    rows = np.array(rows)
    got, e_got = rows.mean(0), rows.std(0, ddof=1) / 2.0
    for i, h in ((0, 0.5), (1, 20.0)):
        sides = []
        for sign in (1, -1):
            vals = np.array([block(render(P0.at[i].add(sign * h), 100 + 10 * sign + s).stack) for s in range(4)])
            sides.append((vals.mean(0), vals.std(0, ddof=1) / 2.0))
        fd = (sides[0][0] - sides[1][0]) / (2 * h)
        e_fd = np.hypot(sides[0][1], sides[1][1]) / (2 * h)
        z = (got[:, i] - fd) / np.hypot(e_got[:, i], e_fd)
        assert np.all(np.abs(z) <= K), (i, got[:, i], fd, z)
        assert np.all(np.abs(fd) > 3 * e_fd), (i, fd, e_fd)  # resolved


def test_pixels_no_photon_reached_have_finite_zero_gradients():
    """A narrow beam leaves most of a wide view dark: those pixels' values and derivatives are 0."""
    wide = rd.Endoscope(beta_deg=0.0, fov_deg=100.0, width=8, height=8, distance=1.0)
    got, rep = replayed_render(tissue(P0), wide, photons=3000, key=jax.random.key(1), options=OPTIONS,
                               illumination=rd.Floodlight(0.05))
    dark = ~got.covered
    assert dark.sum() > 10
    jac = np.asarray(jax.jacfwd(lambda p: rep.stack(tissue(p)))(P0))  # [bands, H, W, 2]
    assert np.all(np.isfinite(jac))
    assert np.all(jac[:, dark] == 0)


@pytest.mark.slow
def test_fluorescence_image_gradient_in_the_concentration():
    """Violet light on PpIX tissue: d(red pixels)/d c from the replayed render vs finite differences."""
    bands = tf.BandGrid([400.0, 640.0], 16.0)

    def fl_tissue(c):
        optics = tf.LayerOptics([tf.ConstantAbsorption(2.0), tf.protoporphyrin_ix(bands, c=c)], tf.ConstantScattering(100.0, 0.8))
        return tf.SpectralTissue([optics], n=[1.4], thickness=[math.inf], bands=bands)

    def red(c, seed, replay=False):
        call = replayed_render if replay else rd.render
        return call(fl_tissue(c), ENDO, spectrum=tf.BoxcarSpectrum(392.0, 408.0), photons=40_000,
                    key=jax.random.key(seed), options=OPTIONS, illumination=rd.Floodlight(0.6))

    rows = []
    for s in range(4):
        rep = red(10.0, s, replay=True)[1]
        rows.append(float(jax.grad(lambda c: block(rep.stack(fl_tissue(c)))[1])(jnp.asarray(10.0))))
    got, e_got = np.mean(rows), np.std(rows, ddof=1) / 2.0
    sides = [np.array([block(red(10.0 + sign * 3.0, 200 + 10 * sign + s).stack)[1] for s in range(4)]) for sign in (1, -1)]
    fd = (sides[0].mean() - sides[1].mean()) / 6.0
    e_fd = math.hypot(sides[0].std(ddof=1) / 2, sides[1].std(ddof=1) / 2) / 6.0
    assert abs(fd) > 3 * e_fd
    assert abs(got - fd) <= K * math.hypot(e_got, e_fd), (got, e_got, fd, e_fd)


def _brute_force_kernels(kernel):
    """A small replay render with `kernel` and its records' surface kernel weights K [pixels, n]
    computed directly (float32 positions, as the maps hold them)."""
    import dataclasses

    from tissuefit.photonmap._kernels import kernel_weight

    options = dataclasses.replace(OPTIONS, kernel=kernel)
    got, rep = replayed_render(tissue(P0), ENDO, photons=5_000, key=jax.random.key(3), options=options,
                               illumination=rd.Floodlight(0.6))
    sh, r = rep.shading, rep.shading.radii[0]
    n = int(rep.surface.records.count)
    xy = np.asarray(rep.surface.records.position, np.float32)[:n, :2].astype(np.float64)
    q = np.asarray(sh.q_xy, np.float32).astype(np.float64)
    d2 = ((q[:, None, :] - xy[None, :, :]) ** 2).sum(-1)
    return got, rep, n, np.asarray(kernel_weight(jnp.asarray(d2), jnp.asarray(r * r), kernel=kernel, dim=2))


@pytest.mark.parametrize("kernel", ["epanechnikov", "box"])
def test_replay_variance_is_the_sum_of_squared_contributions(kernel):
    """`RenderReplay.variance` (squared kernel as a map kernel) against the brute-force sum of
    (K_i P_i)^2 over every record, at the traced tissue and at another."""
    got, rep, n, k = _brute_force_kernels(kernel)
    sh = rep.shading
    assert rep.has_variance
    for p in (P0, P0 * jnp.asarray([1.2, 0.9])):
        power = np.asarray(rep.surface.power(tissue(p)))[:n]
        want = (k**2 @ power**2) * np.asarray(sh.t_surface)[:, None] ** 2
        want = np.where(np.asarray(rep.hit).reshape(-1)[:, None], want, 0.0).T.reshape(-1, *rep.hit.shape)
        want = want * np.asarray(rep.transmission)[:, None, None] ** 2
        np.testing.assert_allclose(np.asarray(rep.variance(tissue(p))), want, rtol=1e-4, atol=1e-6 * want.max())
    # noise_weights: W_ib = sum_p w_bp (K_pi t_p)^2 T_b^2 over hit pixels, so that
    # sum_p w_p variance_p = sum_i,b W_ib P_ib^2 at any tissue (what a fit's J^T J takes out)
    w_pix = np.random.default_rng(1).uniform(0.5, 2.0, got.stack.shape)
    kt = k * (np.asarray(sh.t_surface) * np.asarray(rep.hit).reshape(-1))[:, None]  # [pixels, n]
    want_w = np.einsum("bq,qi->ib", w_pix.reshape(w_pix.shape[0], -1), kt**2) * np.asarray(rep.transmission)[None, :] ** 2
    got_w = np.asarray(rep.noise_weights(w_pix))
    np.testing.assert_allclose(got_w[:n], want_w, rtol=1e-4, atol=1e-6 * want_w.max())
    assert not np.any(got_w[n:])  # padding records weigh nothing
    other = tissue(P0 * jnp.asarray([1.2, 0.9]))
    power = np.asarray(rep.surface.power(other))
    np.testing.assert_allclose(np.sum(w_pix * np.asarray(rep.variance(other))), np.sum(got_w * power**2), rtol=1e-5)


def _functionals(shape, seed=0):
    """Three image functionals [3, bands, H, W], correlated with each other through the kernel:
    the central block's mean, a signed random pattern and one pixel."""
    rng = np.random.default_rng(seed)
    w = np.zeros((3, *shape))
    w[0][BLOCK] = 1.0 / 16
    w[1] = rng.normal(size=shape)
    w[2][1, 4, 3] = 1.0
    return w


@pytest.mark.parametrize("kernel", ["epanechnikov", "gaussian"])
def test_replay_covariance_is_the_sum_over_records(kernel):
    """`RenderReplay.covariance` against brute-force per-record parts c_im = sum over bands and
    pixels of w_m K_i P_ib, Cov = c^T c - (sum c)(sum c)^T / N, at the traced tissue and at another;
    a one-pixel functional's variance is `variance` less the mean-square term."""
    got, rep, n, k = _brute_force_kernels(kernel)
    sh = rep.shading
    assert rep.surface_only  # no fluorophores: no volume map
    k = k * (np.asarray(sh.t_surface) * np.asarray(rep.hit).reshape(-1))[:, None]
    w = _functionals(got.stack.shape)
    w_pix = w.reshape(3, w.shape[1], -1) * np.asarray(rep.transmission)[None, :, None]  # [m, bands, P]
    for p in (P0, P0 * jnp.asarray([1.2, 0.9])):
        power = np.asarray(rep.surface.power(tissue(p)))[:n]  # [n, bands]
        c = np.einsum("mbq,qi,ib->im", w_pix, k, power)
        want = c.T @ c - np.outer(c.sum(0), c.sum(0)) / got.photons
        cov = rep.covariance(tissue(p), w)
        np.testing.assert_allclose(cov, want, rtol=1e-4, atol=1e-6 * np.abs(want).max())
    assert got.photons == float(rep.photons)
    if kernel == "epanechnikov":
        var = np.asarray(rep.variance(tissue(P0)))[1, 4, 3]
        mean = got.maps.surface[1, 4, 3]
        np.testing.assert_allclose(rep.covariance(tissue(P0), w[2:])[0, 0], var - mean**2 / got.photons, rtol=1e-4)


def test_replay_covariance_refuses_weights_of_another_shape():
    rep = replayed(P0, 3)[1]
    with pytest.raises(ValueError, match=r"weights have shape \(2, 8, 8\); expected \[m, 2, 8, 8\]"):
        rep.covariance(tissue(P0), np.zeros((2, 8, 8)))


@pytest.mark.slow  # 8 renders, ~30 s on 2 cores (the exactness test above runs by default)
def test_replay_variance_predicts_the_spread_between_keys():
    """Sum (K_i P_i)^2 is the Monte Carlo variance of a pixel: renders at 8 keys."""
    outs = [replayed(P0, 40 + s) for s in range(8)]
    stacks = np.array([o.stack for o, _ in outs])
    pred = np.mean([np.asarray(r.variance(tissue(P0))) for _, r in outs], axis=0)
    mean = stacks.mean(0)
    ok = mean > 0.1 * mean.max()
    ratio = stacks.var(0, ddof=1)[ok].mean() / pred[ok].mean()
    # 7 degrees of freedom per pixel over ~100 correlated pixels: a relative sd of about 0.1
    assert 0.7 < ratio < 1.4, ratio
    # the covariance of image functionals (pixels correlated through the kernel) against the spread of
    # the same functionals over the 8 keys: each empirical variance is chi^2 with 7 degrees of freedom
    # times the true one / 7, here within its two-sided 99 % interval
    from scipy.stats import chi2

    w = _functionals(stacks.shape[1:])
    f = np.einsum("mbhw,kbhw->km", w, stacks)
    pred_cov = np.mean([r.covariance(tissue(P0), w) for _, r in outs], axis=0)
    emp = np.cov(f, rowvar=False)
    lo, hi = chi2(7).ppf([0.005, 0.995]) / 7
    for m in range(3):
        assert lo < emp[m, m] / pred_cov[m, m] < hi, (m, emp[m, m], pred_cov[m, m])


def test_replay_variance_needs_a_squarable_kernel():
    import dataclasses

    options = dataclasses.replace(OPTIONS, kernel="gaussian")
    rep = replayed_render(tissue(P0), ENDO, photons=2_000, key=jax.random.key(3), options=options,
                          illumination=rd.Floodlight(0.6))[1]
    assert not rep.has_variance
    with pytest.raises(ValueError, match=r"kernel 'box' or 'epanechnikov'; got k = None, kernel = 'gaussian'"):
        rep.variance(tissue(P0))
