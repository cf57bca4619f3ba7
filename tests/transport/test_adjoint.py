"""Fluorescence by adjoint paths from the camera (`_adjoint.py`): the fluence grid against the
tracer's own absorption tally and against analytic interpolation, the camera paths' launch weights,
and the adjoint image against the per-photon brute-force reference and against the emission-site
estimator (the same expectation, different algorithms)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tissuefit as tf
from tissuefit.transport import PinholeCamera, trace_image, trace_spectral
from tissuefit.transport._adjoint import CameraPaths, FluenceGrid, camera_footprint
from tissuefit.transport._nee import ImageSpec

from .test_image import _fluorescent_tissue, assert_matches_the_brute_force_reference

BANDS = tf.BandGrid.uniform(400, 416, 16)


def _grid(**kw):
    base = dict(x0=-0.1, y0=-0.2, dx=0.05, dy=0.04, nx=4, ny=10, z_edges=(0.0, 0.01, 0.03, 0.06, 0.1), bands=(0,), batches=2)
    return FluenceGrid(**(base | kw))


def test_grid_voxels_are_found_and_points_outside_are_not():
    grid = _grid()
    x = jnp.asarray([-0.099, 0.099, 0.01, 0.5, 0.0, 0.0])
    y = jnp.asarray([-0.199, 0.199, 0.05, 0.0, 0.5, 0.0])
    z = jnp.asarray([0.0, 0.099, 0.02, 0.01, 0.01, 0.2])
    index, inside = grid.voxel(x, y, z)
    assert list(np.asarray(inside)) == [True, True, True, False, False, False]
    # (iz, iy, ix) = (1, 6, 2) for the third point: z 0.02 in [0.01, 0.03), y 0.05 in [0.04, 0.08), x 0.01 in [0.0, 0.05)
    assert list(np.asarray(index)[:3]) == [0, grid.voxels - 1, (1 * grid.ny + 6) * grid.nx + 2]


def test_grid_refuses_bad_geometry_naming_the_field():
    with pytest.raises(ValueError, match="grid.z_edges"):
        _grid(z_edges=(0.01, 0.02))
    with pytest.raises(ValueError, match="grid.dx"):
        _grid(dx=0.0)
    with pytest.raises(ValueError, match="grid.bands"):
        _grid(bands=())


def test_fluence_smoothing_chooses_a_width_per_band_and_treats_batches_alike():
    """SURE per excitation band: a band whose fluence is flat under its noise gets a wide kernel, a
    band with a sharp lateral step and little noise stays (nearly) unsmoothed; the same linear map is
    applied to every batch (their mean is the smoothed mean)."""
    from tissuefit.transport._adjoint import smooth_fluence, smooth_like

    grid = _grid(nx=24, ny=24, z_edges=(0.0, 0.01, 0.02), bands=(0, 1), batches=16)
    rng = np.random.default_rng(0)
    truth = np.ones((2, 2, 24, 24))  # [bands, nz, ny, nx]
    truth[1, :, :, 12:] = 20.0  # band 1: a sharp step across x
    noise = np.asarray([1.0, 0.01])[:, None, None, None]
    batches = truth[None] + noise[None] * rng.standard_normal((16, 2, 2, 24, 24))
    smoothed, widths = smooth_fluence(batches.reshape(16, 2, -1), grid)
    assert widths.shape == (2,)
    assert widths[0] >= 3.0 and widths[1] <= 0.5, widths
    out = smoothed.reshape(16, 2, 2, 24, 24)
    assert np.abs(out[:, 0].mean(0) - 1.0).max() < 0.25  # band 0's noise (sd 0.25 per cell in the mean) is gone
    mean_smoothed = smooth_like(batches.mean(0).reshape(2, -1), grid, widths).reshape(2, 2, 24, 24)
    np.testing.assert_allclose(out.mean(0), mean_smoothed, rtol=1e-12, atol=1e-12)


def test_camera_path_weights_average_to_one_over_each_pixel():
    """Uniform points on the image plane weighted by A / (|d|^3 Omega): each pixel's weights average
    to 1 (the solid angle they sample is the pixel's)."""
    camera = PinholeCamera(position=(0.0, 0.0, -0.5), axis=(0, 0.3, 1), x_axis=(1, 0, 0), y_axis=(0, 1, -0.3),
                           half_width=0.7, width=3, height=2, batches=2)
    grid = _grid(batches=2)
    paths = CameraPaths(fluence=jnp.zeros(grid.shape[:2] + (grid.voxels,)), camera=camera, grid=grid, bands=(1,))
    n = 200_000
    index = jnp.arange(n) * camera.pixels + 4  # pixel 4 only
    u = jax.random.uniform(jax.random.key(0), (n, 2), jnp.float64)
    w = np.asarray(paths.weight(index, u))
    assert abs(w.mean() - 1.0) < 5 * w.std() / math.sqrt(n)
    xy, d = paths.launch(index[:3], u[:3])
    np.testing.assert_allclose(np.linalg.norm(np.asarray(d), axis=1), 1.0, rtol=1e-12)
    # the launch point lies on the ray from the pinhole
    ray = np.asarray(xy) - np.asarray(camera.position[:2])
    np.testing.assert_allclose(ray / 0.5, np.asarray(d)[:, :2] / np.asarray(d)[:, 2:], rtol=1e-9)


def test_footprint_covers_every_pixel_ray():
    camera = PinholeCamera(position=(0.1, 0.0, -0.5), axis=(0, 0, 1), x_axis=(1, 0, 0), y_axis=(0, 1, 0),
                           half_width=0.2, width=4, height=4)
    x0, x1, y0, y1 = camera_footprint(camera)
    np.testing.assert_allclose([x0, x1, y0, y1], [0.0, 0.2, -0.1, 0.1], atol=1e-12)


def test_fluence_grid_absorbs_what_the_tracer_absorbs():
    """sum over voxels of phi_i mua_i V is the absorbed fraction of band i (per launched photon): a
    pencil beam at the grid's centre (the grid reaching 10/mu_eff deep and wide enough to hold all but
    ~1e-3 of it), against the shared-path tally of the same trace. Within 4 standard errors (the
    grids' batch spread, and the tally's)."""
    optics = tf.LayerOptics([tf.ConstantAbsorption(10.0)], tf.ConstantScattering(100.0, 0.8))
    tissue = tf.SpectralTissue([optics], n=[1.4], thickness=[math.inf], bands=BANDS)
    camera = PinholeCamera(position=(0, 0, -1.0), axis=(0, 0, 1), x_axis=(1, 0, 0), y_axis=(0, 1, 0), half_width=0.05,
                           width=2, height=2, batches=8)
    grid = FluenceGrid.covering((-0.2, 0.2, -0.2, 0.2), tissue, (0,), batches=8, cells=40)
    scene = tf.SpectralScene(tissue, source=tf.PencilBeam(), spectrum=tf.BoxcarSpectrum(392.0, 408.0))
    out = trace_spectral(scene, key=jax.random.key(2), photons=40_000, image=ImageSpec(camera=camera, grid=grid, lobe=False))
    absorbed = out.fluence[:, 0] * 10.0 * grid.volumes().reshape(1, -1)  # [batches, voxels]
    per_batch = absorbed.sum(1)
    mean, se = per_batch.mean(), per_batch.std(ddof=1) / math.sqrt(len(per_batch))
    assert abs(mean - out.a[0]) < 4 * math.hypot(se, 2e-3 * out.a[0]), (mean, out.a[0], se)
    assert out.image[:, 1].sum() == 0  # a grid pass scores no fluorescence band


@pytest.mark.parametrize("lobe", [True])
def test_adjoint_image_matches_the_brute_force_reference_with_fluorescence(lobe):
    """The adjoint estimate of fluorescence (band 1) with the lights' next-event estimate of the
    scattered light (band 0), against the per-photon tracer with sampled conversions (as
    test_image's check of the emission-site estimator): the image's total and its quadrants, each
    within 4.5 standard errors, and their chi^2."""
    tissue = _fluorescent_tissue()
    camera = PinholeCamera(position=(0.02, 0.0, -1.0), axis=(0, 0, 1), x_axis=(1, 0, 0), y_axis=(0, 1, 0),
                           half_width=0.06, width=6, height=6, batches=40)
    scene = tf.SpectralScene(tissue, source=tf.PencilBeam(), spectrum=tf.BoxcarSpectrum(392.0, 408.0))
    fast = trace_image(scene, camera, key=jax.random.key(3), photons=200_000, lobe=lobe, fluorescence="adjoint",
                       paths=400)
    assert_matches_the_brute_force_reference(tissue, scene, camera, fast)


def test_adjoint_and_emission_sites_agree_pixel_block_by_block_with_a_lesion():
    """Two estimators of the same fluorescence image, with a lesion region (its own fluorophore
    concentration: the grid's fluence is continuous across it, the emission is the region's):
    8 x 8 blocks of pixels within 4.5 combined standard errors, chi^2 over them."""
    dye = lambda c: tf.Fluorophore(name="dye", bands=BANDS, specific_absorption=[5.0, 0.0],  # noqa: E731
                                   eem=[[0.0, 1.0], [0.0, 0.0]], d=1.0, c=c, quantum_yield=0.5)
    layer = tf.LayerOptics([tf.ConstantAbsorption(2.0), dye(0.2)], tf.ConstantScattering(50.0, 0.8))
    lesion = tf.LayerOptics([tf.ConstantAbsorption(2.0), dye(2.0)], tf.ConstantScattering(50.0, 0.8))
    region = tf.Sphere((0.03, 0.0, 0.02), 0.05, optics=lesion)
    tissue = tf.SpectralTissue([layer], n=[1.37], thickness=[math.inf], bands=BANDS, regions=[region])
    camera = PinholeCamera(position=(0.0, 0.0, -0.5), axis=(0, 0, 1), x_axis=(1, 0, 0), y_axis=(0, 1, 0),
                           half_width=0.2, width=16, height=16, batches=32)
    scene = tf.SpectralScene(tissue, source=tf.FlatBeam(radius=0.3), spectrum=tf.BoxcarSpectrum(392.0, 408.0))
    adj = trace_image(scene, camera, key=jax.random.key(4), photons=100_000, fluorescence="adjoint", paths=128)
    sites = trace_image(scene, camera, key=jax.random.key(5), photons=300_000, fluorescence="sites", splits=2)

    def blocks(b):
        return b[:, 1].reshape(b.shape[0], 4, 4, 4, 4).sum((2, 4)).reshape(b.shape[0], -1)

    a, s = blocks(adj.batches), blocks(sites.batches)
    z = (a.mean(0) - s.mean(0)) / np.sqrt(a.var(0, ddof=1) / a.shape[0] + s.var(0, ddof=1) / s.shape[0])
    assert np.all(np.abs(z) < 4.5), z
    assert float(np.sum(z**2)) < z.size + 4 * math.sqrt(2 * z.size), z


def test_adjoint_image_tangents_match_finite_differences():
    """The derivatives of the image with fluorescence from the camera (the lights' pass tallies the
    fluence's derivative by the likelihood ratio, the camera's paths differentiate their weights,
    the fluence and the emission), summed over the image per band, against central differences of
    independent renders at +-h, in the layer's mua, mus, g and the dye's concentration."""
    import equinox as eqx

    base = _fluorescent_tissue()
    where = lambda t: (t.layers[0].absorbers[0].mua, t.layers[0].scattering.mus, t.layers[0].scattering.g,  # noqa: E731
                       t.layers[0].absorbers[1].c)

    def tissue_of(x):
        return eqx.tree_at(where, base, (x[0], x[1], x[2], x[3]))

    def scene_of(t):
        return tf.SpectralScene(t, source=tf.FlatBeam(radius=0.1), spectrum=tf.BoxcarSpectrum(392.0, 408.0))

    x0 = jnp.asarray([2.0, 50.0, 0.8, 1.0])
    eye = jnp.eye(4)
    tangents = tuple(jax.jvp(tissue_of, (x0,), (eye[k],))[1] for k in range(4))
    camera = PinholeCamera(position=(0.0, 0.0, -1.0), axis=(0, 0, 1), x_axis=(1, 0, 0), y_axis=(0, 1, 0),
                           half_width=0.06, width=6, height=6, batches=16)
    # one grid for every render (the default follows mu_eff: each h would compile anew)
    grid = FluenceGrid.covering(camera_footprint(camera), tissue_of(x0), (0,), batches=16, emission_bands=(1,), cells=32)
    run = lambda x, key, **kw: trace_image(scene_of(tissue_of(x)), camera, key=key, photons=40_000,  # noqa: E731
                                           fluorescence="adjoint", paths=64, grid=grid, **kw)
    got = run(x0, jax.random.key(0), tangents=tangents)
    lr = got.tangent_batches.sum((-2, -1))  # [batches, K, bands]
    lr_mean, lr_se = lr.mean(0), lr.std(0, ddof=1) / math.sqrt(lr.shape[0])
    h = [0.3, 4.0, 0.03, 0.15]
    for k in range(4):
        totals = [run(x0 + s * h[k] * eye[k], jax.random.key(10 + 2 * k + i)).batches.sum((-2, -1)) for i, s in enumerate((1, -1))]
        fd = (totals[0].mean(0) - totals[1].mean(0)) / (2 * h[k])
        fd_se = np.sqrt(sum(t.var(0, ddof=1) / t.shape[0] for t in totals)) / (2 * h[k])
        z = (lr_mean[k] - fd) / np.hypot(lr_se[k], fd_se)
        assert np.all(np.abs(z) < 4), (k, lr_mean[k], fd, z)
    # the fluorescence band's derivatives in mua and c are resolved well beyond their noise
    assert np.all(lr_se[[0, 3], 1] < 0.3 * np.abs(lr_mean[[0, 3], 1]))
