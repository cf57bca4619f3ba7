"""The multi-spectral tracer with fluorescence (`trace_spectral`): against the single-band tracer,
the per-photon spectral reference, closed-form fluorescence, and its own exact bookkeeping.

Tolerances are K combined standard errors (per-photon moments); identities to float64 rounding.
"""

import math

import jax
import numpy as np
import pytest

import tissuefit as tf
from tissuefit.transport import _trace
from tissuefit.transport._reference_spectral import trace_spectral_reference

K = 3.5
INF = math.inf
F64 = tf.TraceOptions(precision="float64", lanes=4096)


def agree(a, ea, b, eb, what, k=K):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    bound = k * np.hypot(ea, eb) + 1e-15
    assert np.all(np.abs(a - b) <= bound), f"{what}: {a} vs {b} (bound {bound})"


def layer(mua, mus, g, *fluorophores):
    return tf.LayerOptics([tf.ConstantAbsorption(mua), *fluorophores], tf.ConstantScattering(mus, g))


def three_bands():
    return tf.BandGrid([400.0, 416.0, 640.0], 16.0)


def fluorescent_scene(regions=(), c=100.0):
    """One finite layer with PpIX (strong, so that fluorescence is resolved with few photons)."""
    bands = three_bands()
    tissue = tf.SpectralTissue(
        [layer([5.0, 4.5, 4.0], [50.0, 48.0, 45.0], 0.8, tf.protoporphyrin_ix(bands, c=c))],
        n=[1.37], thickness=[0.2], bands=bands, regions=regions,
    )
    return tf.SpectralScene(tissue)


def reference(scene, photons, seed, boost=1.0):
    """The per-photon spectral reference on the same scene (arrays from the scene's models)."""
    t = scene.tissue
    mua, mus, g = (np.asarray(a) for a in t.properties())
    conv = np.asarray(t.conversion())
    nl = t.num_layers
    regions = []
    for r, region in enumerate(t.regions):
        shape = (
            {"kind": "sphere", "center": tuple(np.asarray(region.center)), "radius": float(region.radius)}
            if isinstance(region, tf.Sphere)
            else {"kind": "box", "lower": tuple(np.asarray(region.lower)), "upper": tuple(np.asarray(region.upper))}
        )
        m = nl + r
        regions.append({**shape, "layer": region.layer, "mua": mua[m], "mus": mus[m], "g": g[m], "conversion": conv[m]})
    geo = t.geometry
    return trace_spectral_reference(
        n=np.asarray(geo.n), thickness=np.asarray(geo.thickness), n_above=float(geo.n_above),
        n_below=float(geo.n_below), mua=mua[:nl], mus=mus[:nl], g=g[:nl], conversion=conv[:nl],
        band_power=np.asarray(scene.band_power()), photons=photons, seed=seed, conversion_boost=boost,
        regions=tuple(regions),
    )


# ---------------------------------------------------------------------------------------------
# Without fluorescence: the single-band tracer


@pytest.mark.parametrize("mode", ["per_band", "shared"])
def test_one_band_is_the_single_band_tracer_exactly(key, mode):
    """One band, no fluorophore: the same photons take the same random numbers, so the spectral
    tracer reproduces the foundation tracer to float64 rounding."""
    bands = tf.BandGrid([500.0], 16.0)
    tissue = tf.SpectralTissue([layer(1.0, 100.0, 0.9), layer(3.0, 20.0, 0.0)], n=[1.4, 1.33],
                               thickness=[0.05, INF], bands=bands)
    got = tf.trace_spectral(tf.SpectralScene(tissue), key=key, photons=20_000, options=F64,
                            spectral=tf.SpectralOptions(mode=mode))
    want = tf.trace(tf.Scene(tissue.at_band(0)), key=key, photons=20_000, options=F64)
    assert got.mode == mode
    np.testing.assert_allclose(got.rd[0], want.rd, rtol=1e-10)
    np.testing.assert_allclose(got.tt[0], want.tt, rtol=1e-10)
    np.testing.assert_allclose(got.rsp_total, want.rsp, rtol=1e-12)
    # shared paths take the heat from the balance, which leaves out roulette's zero-mean gain
    expected_a = want.a if mode == "per_band" else want.a - want.roulette
    np.testing.assert_allclose(got.a[0], expected_a, rtol=1e-9)


@pytest.mark.parametrize("mode", ["per_band", "shared"])
def test_each_band_matches_a_single_band_run(key, mode):
    bands = three_bands()
    tissue = tf.SpectralTissue([layer([2.0, 2.5, 1.5], [60.0, 55.0, 50.0], 0.8)], n=[1.37], thickness=[0.1], bands=bands)
    scene = tf.SpectralScene(tissue)
    got = tf.trace_spectral(scene, key=key, photons=60_000, spectral=tf.SpectralOptions(mode=mode))
    power = np.asarray(scene.band_power())
    for b in range(3):
        want = tf.trace(tf.Scene(tissue.at_band(b)), key=jax.random.key(b + 11), photons=20_000)
        agree(got.rd[b], got.rd_stderr[b], power[b] * want.rd, power[b] * want.rd_stderr, f"rd band {b}")
        agree(got.tt[b], got.tt_stderr[b], power[b] * want.tt, power[b] * want.tt_stderr, f"tt band {b}")
    assert np.all(got.rd_fluor == 0) and np.all(got.emitted == 0)


# ---------------------------------------------------------------------------------------------
# With fluorescence: the per-photon reference


@pytest.fixture(scope="module")
def fluorescent_reference():
    return reference(fluorescent_scene(), photons=12_000, seed=5)


@pytest.mark.parametrize("mode,boost", [("per_band", 1.0), ("per_band", 5.0), ("shared", 1.0)])
def test_fluorescence_matches_the_reference(key, fluorescent_reference, mode, boost):
    ref = fluorescent_reference
    got = tf.trace_spectral(fluorescent_scene(), key=key, photons=100_000,
                            spectral=tf.SpectralOptions(mode=mode, conversion_boost=boost))
    assert got.mode == mode
    assert ref["rd_fluor"][2] > 10 * ref["rd_fluor_stderr"][2]  # the test resolves fluorescence
    for name in ("rd", "tt", "rd_fluor", "tt_fluor"):
        agree(getattr(got, name), getattr(got, f"{name}_stderr"), ref[name], ref[f"{name}_stderr"], f"{mode} {name}")
    # emission only at and beyond the excitation band (Stokes), here into 640 nm only
    assert got.emitted[0] == pytest.approx(0.0, abs=1e-12) and got.emitted[2] > 0


def test_regions_match_the_reference(key):
    """A PpIX sphere (a cap: its centre lies 0.02 cm below the surface, radius 0.05 cm) and a
    strongly absorbing box in a collagen-free layer: exact region boundaries against the reference."""
    bands = three_bands()
    lesion = tf.Sphere([0.0, 0.0, 0.02], 0.05, optics=layer([5.0, 4.5, 4.0], [80.0, 75.0, 70.0], 0.8,
                                                            tf.protoporphyrin_ix(bands, c=300.0)))
    absorber = tf.Box([0.08, -0.1, 0.0], [0.2, 0.1, 0.1], optics=layer(30.0, 50.0, 0.8))
    scene = tf.SpectralScene(tf.SpectralTissue(
        [layer(2.0, 50.0, 0.8)], n=[1.37], thickness=[0.2], bands=bands, regions=(lesion, absorber)))
    ref = reference(scene, photons=12_000, seed=9)
    got = tf.trace_spectral(scene, key=key, photons=100_000)
    for name in ("rd", "tt", "rd_fluor", "tt_fluor"):
        agree(getattr(got, name), getattr(got, f"{name}_stderr"), ref[name], ref[f"{name}_stderr"], f"regions {name}")
    assert got.rd_fluor[2] > 5 * got.rd_fluor_stderr[2]


def test_region_with_the_layers_properties_changes_nothing(key):
    base = fluorescent_scene()
    same = base.tissue.layers[0]
    with_region = fluorescent_scene(regions=(tf.Sphere([0.01, 0.0, 0.05], 0.04, optics=same),))
    a = tf.trace_spectral(base, key=key, photons=60_000)
    b = tf.trace_spectral(with_region, key=jax.random.key(77), photons=60_000)
    for name in ("rd", "tt", "rd_fluor"):
        agree(getattr(a, name), getattr(a, f"{name}_stderr"), getattr(b, name), getattr(b, f"{name}_stderr"), name)


# ---------------------------------------------------------------------------------------------
# Closed form and bookkeeping


def test_non_scattering_fluorescence_has_the_closed_form(key):
    """Index-matched semi-infinite medium, mus = 0, a fluorophore absorbing only band 0 and
    emitting only into band 1. Photons absorbed at depth z (density mua0 exp(-mua0 z)) convert
    with probability phi mua_f / mua0 and emit isotropically; an upward cosine mu escapes with
    probability exp(-mua1 z / mu). Integrating over z and mu,

        F_1 = phi (mua_f / mua0) (1/2) [1 - a ln((1 + a) / a)],   a = mua1 / mua0.
    """
    bands = tf.BandGrid([450.0, 600.0], 20.0)
    phi, sigma = 0.5, 2.0  # yield; fluorophore absorption [1/cm] at d = c = 1
    eem = np.array([[0.0, 1.0], [0.0, 0.0]])
    fluor = tf.Fluorophore(name="test", bands=bands, specific_absorption=[sigma, 0.0], eem=eem, d=1.0, c=1.0,
                           quantum_yield=phi)
    tissue = tf.SpectralTissue([layer([1.0, 1.5], 0.0, 0.0, fluor)], n=[1.0], thickness=[INF], bands=bands)
    scene = tf.SpectralScene(tissue, spectrum=tf.BoxcarSpectrum(440.0, 460.0))
    got = tf.trace_spectral(scene, key=key, photons=200_000, options=F64)
    mua0, mua1 = 1.0 + sigma, 1.5
    a = mua1 / mua0
    expected = phi * (sigma / mua0) * 0.5 * (1.0 - a * math.log((1.0 + a) / a))
    assert got.active == (0, 1)
    agree(got.rd_fluor[1], got.rd_fluor_stderr[1], expected, 0.0, "escaping fluorescence")
    # every launched photon is absorbed at its first interaction: the emitted weight is exact
    np.testing.assert_allclose(got.emitted[1], phi * sigma / mua0, rtol=1e-10)  # float64 sums of 2e5 terms


def test_bookkeeping_is_exact_per_band(key):
    """Per band: launched + emitted = rd + tt + a + converted + reconverted - roulette (per_band
    mode, float64, conversion_boost 1: the energy of every photon is conserved), in total
    rsp + rd + tt + a - roulette = 1, and emitted light is all accounted for. (Boosted conversion
    splits create and destroy weight with zero mean: then these hold in expectation only.)"""
    got = tf.trace_spectral(fluorescent_scene(), key=key, photons=20_000, options=F64,
                            spectral=tf.SpectralOptions(mode="per_band"))
    lhs = got.launched + got.emitted
    rhs = got.rd + got.tt + got.a + got.converted + got.reconverted - got.roulette
    np.testing.assert_allclose(lhs, rhs, rtol=0, atol=1e-10)
    np.testing.assert_allclose(got.emitted.sum(), got.converted.sum() + got.reconverted.sum(), rtol=1e-10)
    fluor_out = got.rd_fluor + got.tt_fluor + got.a_fluor + got.reconverted - got.roulette_fluor
    np.testing.assert_allclose(got.emitted.sum(), fluor_out.sum(), rtol=1e-9)
    total = got.rsp_total + got.rd.sum() + got.tt.sum() + got.a.sum() - got.roulette.sum()
    assert total == pytest.approx(1.0, abs=1e-10)


def test_thin_sample_emits_the_eem_shape(key):
    """A thin sample (20 µm; re-absorption of the emission below 0.2 %): escaping fluorescence per
    band has the shape of the EEM row of the excitation band."""
    bands = tf.BandGrid.uniform(400, 720, 16)
    ppix = tf.protoporphyrin_ix(bands, c=50.0, quantum_yield=1.0)
    tissue = tf.SpectralTissue([layer(0.01, 1.0, 0.0, ppix)], n=[1.0], thickness=[0.002], bands=bands)
    scene = tf.SpectralScene(tissue, spectrum=tf.BoxcarSpectrum(392.0, 408.0))
    got = tf.trace_spectral(scene, key=key, photons=200_000, spectral=tf.SpectralOptions(conversion_boost=50.0))
    escaped = got.rd_fluor + got.tt_fluor
    err = np.hypot(got.rd_fluor_stderr, got.tt_fluor_stderr)
    shape = np.asarray(ppix.emission())[0]
    scale = escaped.sum() / shape.sum()
    main = shape >= 0.01 * shape.sum()  # bands holding >= 1 % of the emission (few photons elsewhere)
    agree(escaped[main], err[main], scale * shape[main], 0.0, "emission shape", k=4.0)
    assert escaped[~main].sum() < 0.03 * escaped.sum()
    assert escaped[np.argmax(shape)] > 10 * err[np.argmax(shape)]


# ---------------------------------------------------------------------------------------------
# Records, skipping, configuration


def test_surface_records_sum_to_rd_and_overflow_is_reported(key):
    scene = fluorescent_scene()
    got = tf.trace_spectral(scene, key=key, photons=5_000, records=tf.RecordSpec(surface=100_000, volume=100_000))
    surf = got.surface_records
    assert surf.overflow == 0 and surf.count > 0
    np.testing.assert_allclose(surf.power.sum(0), got.rd, rtol=1e-5, atol=1e-12)
    np.testing.assert_allclose(surf.position[:, 2], 0.0)
    assert np.all(surf.direction[:, 2] < 0)  # leaving the tissue upwards
    np.testing.assert_allclose(np.linalg.norm(surf.direction, axis=1), 1.0, rtol=1e-5)
    vol = got.volume_records
    assert vol.count > 0 and np.all(vol.converted) and np.all(vol.position[:, 2] > 0)
    small = tf.trace_spectral(scene, key=key, photons=5_000, records=tf.RecordSpec(surface=64))
    assert small.surface_records.count == 64
    assert small.surface_records.count + small.surface_records.overflow == surf.count
    assert small.volume_records is None


@pytest.mark.parametrize("mode", ["per_band", "shared"])
def test_lane_count_changes_only_the_order_of_sums(key, mode):
    """A photon's random numbers follow its index, not its lane: 64 lanes (each harvest books its
    escapes in many gathered passes of 64 / HARVEST_SHARE rows) and 4096 lanes (one pass) give the
    same tallies to float64 rounding and the same surface records."""
    scene = fluorescent_scene()

    def run(lanes):
        return tf.trace_spectral(scene, key=key, photons=3_000, spectral=tf.SpectralOptions(mode=mode),
                                 options=tf.TraceOptions(precision="float64", lanes=lanes), records=tf.RecordSpec(surface=50_000))

    few, many = run(64), run(4096)
    for name in ("rd", "tt", "rd_fluor", "rd_stderr", "tt_stderr", "emitted", "converted"):
        np.testing.assert_allclose(getattr(few, name), getattr(many, name), rtol=1e-9, atol=1e-15, err_msg=name)
    assert few.rd_fluor.sum() > 0
    a, b = few.surface_records, many.surface_records
    assert a.count == b.count > 500
    order_a, order_b = np.lexsort((a.position[:, 0], a.photon)), np.lexsort((b.position[:, 0], b.photon))
    np.testing.assert_array_equal(a.photon[order_a], b.photon[order_b])
    np.testing.assert_allclose(a.power[order_a], b.power[order_b], rtol=1e-9, atol=1e-18)


def test_shared_records_carry_band_powers(key):
    scene = fluorescent_scene()
    got = tf.trace_spectral(scene, key=key, photons=5_000, spectral=tf.SpectralOptions(mode="shared"),
                            records=tf.RecordSpec(surface=100_000))
    np.testing.assert_allclose(got.surface_records.power.sum(0), got.rd, rtol=1e-4, atol=1e-12)


def test_no_fluorophore_means_no_conversion_code():
    """Skip what is not needed: the compiled step of a scene without fluorophores draws no
    conversion numbers and has no conversion loop; bands without light carry no weight."""
    import jax.numpy as jnp

    from tissuefit.transport import _spectral_state as S
    from tissuefit.transport._spectral import SpectralKernel, _Inputs, resolve_config

    def step_jaxpr(scene):
        config = resolve_config(scene, tf.TraceOptions(lanes=32), tf.SpectralOptions(mode="per_band"), tf.RecordSpec())
        kernel = SpectralKernel(config)
        inputs = _Inputs(scene)
        medium = kernel.medium(inputs)
        lanes = S.idle_lanes(32, config, jnp.float32)
        acc = S.zeros_acc(config, 1, jnp.float32)
        return str(jax.make_jaxpr(lambda l, a: kernel.step(l, a, medium, inputs))(lanes, acc)), config

    plain, config = step_jaxpr(tf.SpectralScene(tf.SpectralTissue([layer(1.0, 10.0, 0.9)], n=[1.4], thickness=[INF])))
    fluorescent, _ = step_jaxpr(fluorescent_scene())
    assert "while" not in plain and "while" in fluorescent
    assert not config.fluorescent
    violet = tf.SpectralScene(tf.SpectralTissue([layer(1.0, 10.0, 0.9)], n=[1.4], thickness=[INF]), spectrum=tf.violet_led())
    assert len(violet.active_bands()) < 21
    lit = tf.SpectralScene(tf.SpectralTissue([layer(1.0, 10.0, 0.9, tf.protoporphyrin_ix())], n=[1.4], thickness=[INF]),
                           spectrum=tf.violet_led())
    assert set(lit.active_bands()) > set(violet.active_bands())  # PpIX emission reaches the red bands


def test_auto_mode_shares_paths_wherever_they_can_serve():
    from tissuefit.transport._spectral import resolve_config

    def mode(scene):
        return resolve_config(scene, tf.TraceOptions(), tf.SpectralOptions(), tf.RecordSpec()).mode

    paper = tf.SpectralScene(tf.SpectralTissue([layer(20.0, 200.0, 0.9, tf.collagen(), tf.protoporphyrin_ix())],
                                               n=[1.1], thickness=[INF]))
    assert mode(paper) == "shared"
    blood = tf.LayerOptics([tf.Blood(fraction=0.02, saturation=0.7)], tf.PowerLawScattering(18.9, 1.286, 0.9))
    assert mode(tf.SpectralScene(tf.SpectralTissue([blood], n=[1.37], thickness=[INF]))) == "shared"
    uneven = tf.LayerOptics([tf.ConstantAbsorption(1.0)], tf.ConstantScattering(50.0, np.linspace(0.8, 0.9, 21)))
    assert mode(tf.SpectralScene(tf.SpectralTissue([uneven], n=[1.37], thickness=[INF]))) == "per_band"


def test_changing_parameters_does_not_recompile(key):
    _trace._compiled.cache_clear()
    for c in (50.0, 80.0):
        tf.trace_spectral(fluorescent_scene(c=c), key=key, photons=500)
    assert _trace._compiled.cache_info().misses == 1


@pytest.mark.parametrize(
    "make,match",
    [
        (lambda: tf.SpectralOptions(mode="hero"), "spectral.mode"),
        (lambda: tf.SpectralOptions(conversion_boost=0.5), "spectral.conversion_boost"),
        (lambda: tf.RecordSpec(surface=-1), "records.surface"),
        (lambda: tf.Sphere([0, 0, 0.1], -1.0, optics=layer(1.0, 1.0, 0.0)), "region.radius"),
        (lambda: tf.Box([0, 0, 0], [1, -1, 1], optics=layer(1.0, 1.0, 0.0)), r"region.upper\[1\]"),
        (lambda: tf.SpectralTissue([layer(1.0, 1.0, 0.0)], n=[1.4], thickness=[INF],
                                   regions=(tf.Sphere([0, 0, 0.1], 0.1, optics=layer(1.0, 1.0, 0.0), layer=3),)),
         r"regions\[0\].layer"),
        (lambda: tf.SpectralTissue([layer(1.0, 1.0, 0.0)], n=[1.4], thickness=[INF], regions=(
            tf.Sphere([0, 0, 0.1], 0.1, optics=layer(1.0, 1.0, 0.0)),
            tf.Sphere([0, 0, 0.15], 0.1, optics=layer(1.0, 1.0, 0.0)))), "overlap"),
    ],
)
def test_bad_input_names_the_field(make, match):
    with pytest.raises((ValueError, TypeError), match=match):
        make()


def test_shared_mode_refuses_band_dependent_g(key):
    bands = three_bands()
    tissue = tf.SpectralTissue([layer(1.0, 50.0, [0.8, 0.8, 0.9])], n=[1.37], thickness=[INF], bands=bands)
    with pytest.raises(ValueError, match="g differing between bands"):
        tf.trace_spectral(tf.SpectralScene(tissue), key=key, photons=10, spectral=tf.SpectralOptions(mode="shared"))


# ---------------------------------------------------------------------------------------------
# Voxel grids of concentrations


def _ppix_boxes_and_grid(bands):
    inner = layer(2.0, 50.0, 0.8, tf.protoporphyrin_ix(bands, c=1.0))
    boxes = (
        tf.Box([-0.1, -0.1, 0.0], [0.0, 0.1, 0.1], optics=layer(2.0, 50.0, 0.8, tf.protoporphyrin_ix(bands, c=100.0))),
        tf.Box([0.0, -0.1, 0.0], [0.1, 0.1, 0.1], optics=layer(2.0, 50.0, 0.8, tf.protoporphyrin_ix(bands, c=300.0))),
    )
    # 2 x 3 x 2 voxels: x halves at c = 100 and 300; y and z subdivided without changing anything
    c = np.repeat(np.repeat(np.array([100.0, 300.0]).reshape(1, 2, 1, 1), 3, 2), 2, 3)
    grid = tf.VoxelGrid([-0.1, -0.1, 0.0], [0.1, 0.1, 0.1], c, optics=inner)
    return boxes, grid


def test_voxel_grid_equals_the_boxes_it_is_made_of(key):
    """Exact voxel traversal: a grid of two concentrations (with extra, inert subdivisions) gives
    what two boxes with those concentrations give. The beam is off the boxes' common face."""
    bands = three_bands()
    boxes, grid = _ppix_boxes_and_grid(bands)
    source = tf.PencilBeam(x=0.013, y=0.007)

    def run(regions, k):
        tissue = tf.SpectralTissue([layer(2.0, 50.0, 0.8)], n=[1.37], thickness=[0.2], bands=bands, regions=regions)
        return tf.trace_spectral(tf.SpectralScene(tissue, source=source), key=k, photons=60_000)

    a, b = run(boxes, key), run((grid,), jax.random.key(5))
    assert b.mode == "per_band" and b.outcome.successful
    for name in ("rd", "tt", "rd_fluor"):
        agree(getattr(a, name), getattr(a, f"{name}_stderr"), getattr(b, name), getattr(b, f"{name}_stderr"), f"voxels {name}")
    assert b.rd_fluor[2] > 20 * b.rd_fluor_stderr[2]


def test_voxel_grid_properties_and_errors():
    bands = three_bands()
    boxes, grid = _ppix_boxes_and_grid(bands)
    assert grid.num_media == 12
    mua, _, _ = grid.properties(bands)
    np.testing.assert_allclose(mua[0], boxes[0].properties(bands)[0][0], rtol=1e-12)
    np.testing.assert_allclose(mua[-1], boxes[1].properties(bands)[0][0], rtol=1e-12)
    np.testing.assert_allclose(grid.conversion(bands, "photons")[-1], boxes[1].conversion(bands, "photons")[0], rtol=1e-12)
    with pytest.raises(ValueError, match="region.concentration has shape"):
        tf.VoxelGrid([0, 0, 0], [1, 1, 1], np.ones((2, 2, 2, 2)), optics=layer(1.0, 1.0, 0.0, tf.protoporphyrin_ix(bands)))
    with pytest.raises(ValueError, match="region.concentration"):
        tf.VoxelGrid([0, 0, 0], [1, 1, 1], -np.ones((1, 2, 2, 2)), optics=layer(1.0, 1.0, 0.0, tf.protoporphyrin_ix(bands)))
    tissue = tf.SpectralTissue([layer(2.0, 50.0, 0.8)], n=[1.37], thickness=[0.2], bands=bands, regions=(grid,))
    with pytest.raises(ValueError, match="voxel grids are traced per band"):
        tf.trace_spectral(tf.SpectralScene(tissue), key=jax.random.key(0), photons=10, spectral=tf.SpectralOptions(mode="shared"))


@pytest.mark.parametrize("mode", ["per_band", "shared"])
def test_records_path_statistics_reweight_to_a_retrace(key, mode):
    """Records carry (L, n) per medium since launch: reweighting every surface record by
    (mus'/mus)^n exp(-(mut' - mut) L) (docs/design.md §5) reproduces a re-trace at the new parameters."""
    bands = tf.BandGrid([500.0], 16.0)

    def scene(mua, mus):
        return tf.SpectralScene(tf.SpectralTissue([layer([mua], [mus], 0.85)], n=[1.4], thickness=[0.05], bands=bands))

    spectral = tf.SpectralOptions(mode=mode)
    got = tf.trace_spectral(scene(3.0, 60.0), key=key, photons=20_000, spectral=spectral,
                            records=tf.RecordSpec(surface=200_000))
    rec = got.surface_records
    assert rec.path.shape == (rec.count, 1) and rec.hits.shape == (rec.count, 1)
    assert np.all(rec.path > 0) and np.all(rec.hits == np.round(rec.hits))
    # a photon crossing a 0.05 cm layer and back travels at least twice its deepest point
    mua1, mus1 = 4.5, 50.0
    ratio = (mus1 / 60.0) ** rec.hits[:, 0] * np.exp(-((mua1 + mus1) - 63.0) * rec.path[:, 0])
    w = rec.power[:, 0] * ratio
    moved = tf.trace_spectral(scene(mua1, mus1), key=jax.random.fold_in(key, 1), photons=20_000, spectral=spectral)
    err = np.std(w) * np.sqrt(w.size) / 20_000  # per-photon spread of the reweighted estimate
    agree(w.sum(), err, moved.rd[0], moved.rd_stderr[0], "reweighted rd vs re-trace", k=4.0)
    assert abs(w.sum() / got.rd[0] - 1) > 10 * err / got.rd[0]  # the change is resolved, not noise


@pytest.mark.parametrize("mode", ["per_band", "shared"])
def test_emission_records_sum_to_the_emitted_fluorescence(key, mode):
    scene = fluorescent_scene()
    records = tf.RecordSpec(volume=400_000, emission=True)
    got = tf.trace_spectral(scene, key=key, photons=5_000, spectral=tf.SpectralOptions(mode=mode), records=records)
    vol = got.volume_records
    assert vol.overflow == 0 and vol.emission.any() and (~vol.emission).any()
    em = vol.select(vol.emission)
    np.testing.assert_allclose(em.power.sum(0), got.emitted, rtol=1e-4, atol=1e-12)
    assert np.all(em.path == 0) and np.all(em.hits == 0) and np.all(em.converted)
    np.testing.assert_allclose(np.linalg.norm(em.direction, axis=1), 1.0, rtol=1e-5)
    # without emission records the arrivals are the same records as before
    plain = tf.trace_spectral(scene, key=key, photons=5_000, spectral=tf.SpectralOptions(mode=mode),
                              records=tf.RecordSpec(volume=400_000))
    arrivals = vol.select(~vol.emission)
    assert arrivals.count == plain.volume_records.count and not plain.volume_records.emission.any()
    np.testing.assert_allclose(arrivals.power, plain.volume_records.power, rtol=1e-6, atol=1e-15)
    # and without arrivals the emission records alone, the same as with them
    alone = tf.trace_spectral(scene, key=key, photons=5_000, spectral=tf.SpectralOptions(mode=mode),
                              records=tf.RecordSpec(volume=400_000, emission=True, arrivals=False)).volume_records
    assert alone.count == em.count and alone.emission[: alone.count].all()
    np.testing.assert_allclose(alone.valid().power, em.power, rtol=1e-6, atol=1e-15)
