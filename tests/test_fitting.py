"""Tests for fitting/: parameter maps against closed forms, the cached loss against full
renders by diffshade.render with a numpy loss, the jitted step's compilation count,
recovery of known materials, and standard errors against a float64 central-difference
Jacobian of rendered images."""

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiles import compiles

import diffshade as ds
from data_synth import make_dataset
from diffshade.scene.lights import group_lights
from fitting import DEFAULT_INIT, Dataset, FitSpec, IdentifiabilityWarning, View, fit, view_scene
from fitting.driver import FitResult, relative_errors
from fitting.model import build_cache, make_loss
from fitting.model.loss import mean_rho
from fitting.report.misfit import _neighbour_squares
from fitting.report.result import comparison_table, render_rgb
from fitting.report.uncertainty import uncertainty
from fitting.solve import make_optimizer, make_step
from fitting.solve.linear import (
    _fixed_profile,
    _grid_minimum,
    _solve,
    box_least_squares,
    normal_equations,
)
from fitting.spec import (
    material_values,
    param_labels,
    to_material,
    to_unconstrained,
    to_values,
    value_names,
)

TRUTH = dict(ka=(0.35, 0.3, 0.5), kd=(0.6, 0.45, 0.3), ks=(0.4, 0.5, 0.3), shininess=35.0)
SPHERE = ds.icosphere(2)


def truth_material():
    return ds.material(**TRUTH)


@pytest.fixture(scope="module")
def small():
    """2 images (2 cameras x 1 directional light) of a subdivision-2 icosphere, 40 px."""
    return make_dataset(SPHERE, truth_material(), n_views=2, n_lights=1, size=40)


def np_sigmoid(u):
    return 1.0 / (1.0 + np.exp(-np.asarray(u, np.float64)))


# ---- parameters ----


@pytest.mark.parametrize("mode, upper", [("rgb", 1.0), ("grey", 1.0), ("rgb", 2.5)])
def test_param_maps_round_trip(mode, upper):
    spec = FitSpec(ka=mode, kd=mode, ks=mode, upper=upper)
    mat = ds.material(ka=(0.1, 0.2, 0.3), kd=(0.9, 0.5, 0.05), ks=(0.4, 0.4, 0.7),
                      shininess=250.0)
    back = to_material(to_unconstrained(mat, spec), spec, DEFAULT_INIT)
    for name in ("ka", "kd", "ks"):
        expected = np.asarray(getattr(mat, name))
        expected = np.full(3, expected.mean()) if mode == "grey" else expected
        np.testing.assert_allclose(getattr(back, name), expected, rtol=1e-5)
    np.testing.assert_allclose(back.shininess, 250.0, rtol=1e-5)


def test_param_map_is_sigmoid_and_exp_within_bounds():
    spec = FitSpec(upper=2.0)
    u = np.array([-80.0, -3.0, 0.0, 60.0], np.float32)
    params = {"ka": jnp.asarray(u[:3]), "kd": jnp.asarray(u[1:]), "ks": jnp.asarray(u[[0, 2, 3]]),
              "shininess": jnp.asarray(6.5)}
    values = to_values(params, spec)
    for name in ("ka", "kd", "ks"):
        got = np.asarray(values[name])
        np.testing.assert_allclose(got, 2.0 * np_sigmoid(params[name]), rtol=1e-6, atol=1e-30)
        assert np.all((got >= 0) & (got <= 2.0))
    np.testing.assert_allclose(values["shininess"], np.exp(6.5), rtol=1e-6)


def test_fixed_quantities_come_from_the_base_material():
    spec = FitSpec(ka=None, kd="grey", ks=None, shininess=False)
    base = ds.material(ka=(0.1, 0.2, 0.3), kd=0.5, ks=(0.7, 0.6, 0.5), shininess=12.0)
    got = to_material({"kd": jnp.asarray(0.0)}, spec, base)
    np.testing.assert_array_equal(got.ka, base.ka)
    np.testing.assert_array_equal(got.ks, base.ks)
    np.testing.assert_allclose(got.kd, [0.5, 0.5, 0.5])
    assert float(got.shininess) == 12.0


def test_param_labels_group_shininess_positions_and_colours():
    spec = FitSpec(ka="grey", light_colors=True, light_positions=True)
    lights = [group_lights([ds.point_light((1.0, 2.0, 3.0), 0.5),
                               ds.directional_light((0, 0, -1), 0.8)])]
    params = to_unconstrained(DEFAULT_INIT, spec, lights)
    labels = param_labels(params)
    assert labels["shininess"] == "shininess" and labels["ka"] == "colour"
    assert labels["lights"][0]["point"] == {"color": "colour", "position": "position"}
    assert labels["lights"][0]["directional"] == {"color": "colour"}
    names = value_names(to_values(params, spec))
    assert names[:4] == ["ka", "kd[r]", "kd[g]", "kd[b]"]
    assert "lights[0].point[0].position[z]" in names and names[-1] == "shininess"


# ---- cached loss against full renders ----


def cup_mesh():
    """A box without its +z side: from above the opening, its inside shows back faces."""
    cube = ds.box((1.0, 1.0, 1.0))
    return ds.Mesh(cube.vertices, jnp.concatenate([cube.faces[:8], cube.faces[10:]]),
                   cube.normals)


def cup_dataset(shading, two_sided):
    mesh = cup_mesh()
    model = ds.model_matrix(rotate_deg=(20.0, 30.0, 0.0))
    settings = ds.RenderSettings(shading=shading)
    views = []
    for k, eye in enumerate([(0.6, 1.5, 2.2), (-1.8, 0.5, 1.6)]):
        camera = ds.look_at(eye, (0, 0, 0), width=36, height=32)
        lights = group_lights([ds.directional_light((-0.3, -1.0, -0.5), 0.7),
                                  ds.point_light((1.5, 2.0, 2.0), 0.5)])
        mask = np.ones((32, 36), bool)
        mask[:, : 10 * k] = False
        views.append(View(camera, lights, np.zeros((32, 36, 3)), mask if k else None))
    blank = Dataset(mesh, views, model=model, global_ambient=0.3, settings=settings,
                    two_sided=two_sided)
    targets = [np.asarray(ds.render(view_scene(blank, i, truth_material()), settings))[..., :3]
               for i in range(len(views))]
    views = [dataclasses.replace(v, target=t) for v, t in zip(views, targets, strict=True)]
    return dataclasses.replace(blank, views=views)


@pytest.mark.parametrize("shading, two_sided", [("phong", False), ("phong", True),
                                                ("gouraud", True), ("flat", True),
                                                ("flat_last", True)])
def test_cached_loss_equals_full_render_loss(shading, two_sided):
    dataset = cup_dataset(shading, two_sided)
    guess = ds.material(ka=0.2, kd=(0.3, 0.7, 0.5), ks=0.6, shininess=9.0)
    spec = FitSpec()
    data = build_cache(dataset, DEFAULT_INIT, edge_margin=0)
    cached = float(jax.jit(make_loss(spec))(to_unconstrained(guess, spec), data))
    squares, count = 0.0, 0
    for i, view in enumerate(dataset.views):
        image = np.asarray(ds.render(view_scene(dataset, i, guess), dataset.settings))
        kept = image[..., 3] > 0 if view.mask is None else (image[..., 3] > 0) & view.mask
        np.testing.assert_array_equal(np.asarray(data.views[i].pixels), np.flatnonzero(kept))
        diff = image[..., :3][kept].astype(np.float64) - view.target[kept]
        squares, count = squares + np.sum(diff**2), count + diff.size
    assert cached == pytest.approx(squares / count, rel=1e-5)


def test_edge_margin_drops_the_silhouette(small):
    full, inner = (build_cache(small, DEFAULT_INIT, edge_margin=m) for m in (0, 2))
    for a, b in zip(full.views, inner.views, strict=True):
        covered = np.zeros(40 * 40, bool)
        covered[np.asarray(a.pixels)] = True
        covered = covered.reshape(40, 40)
        rows, cols = np.divmod(np.asarray(b.pixels), 40)
        for r, c in zip(rows, cols, strict=True):  # every kept pixel is 2 steps inside
            assert covered[r - 2:r + 3, c].all() and covered[r, c - 2:c + 3].all()
        assert 0 < len(b.pixels) < len(a.pixels)


def test_fixed_geometry_and_panels_compile_no_host_callback(monkeypatch):
    """The fitting cache's rasterization and the result panels' renders run no host
    callback inside a compiled program (so the persistent compilation cache keeps them
    all: the candidate search runs on NumPy arrays between them), yet give render's
    pixels: the same covered pixels, colours equal to float rounding. (24 px: a size no
    other test compiles, so everything here is traced afresh.)"""
    dataset = make_dataset(SPHERE, truth_material(), n_views=1, n_lights=1, size=24)

    def refuse(*args, **kwargs):
        raise AssertionError("a host callback was compiled into a program")
    monkeypatch.setattr(jax, "pure_callback", refuse)
    data = build_cache(dataset, DEFAULT_INIT, edge_margin=0)
    image = render_rgb(dataset, 0, DEFAULT_INIT)
    monkeypatch.undo()
    expected = np.asarray(ds.render(view_scene(dataset, 0, DEFAULT_INIT), dataset.settings))
    np.testing.assert_array_equal(np.asarray(data.views[0].pixels),
                                  np.flatnonzero(expected[..., 3] > 0))
    np.testing.assert_allclose(image, expected[..., :3], atol=2e-6)


def test_the_views_of_one_camera_are_rasterized_once(monkeypatch):
    """A camera's views (one per light) share their geometry: the cache and the panels
    rasterize it once for them, and what they get equals a rasterization of each view on
    its own (cache._last emptied before each), bit for bit."""
    from fitting.model import cache

    dataset = make_dataset(SPHERE, truth_material(), n_views=2, n_lights=2, size=24)
    monkeypatch.setattr(cache, "_last", {})  # not what an earlier test left
    rasterized = []
    once = cache._rasterized
    monkeypatch.setattr(cache, "_rasterized", lambda *a: rasterized.append(a) or once(*a))
    data = build_cache(dataset, DEFAULT_INIT, edge_margin=0)
    assert len(rasterized) == 2  # 2 cameras, 4 views
    panels = [render_rgb(dataset, i, DEFAULT_INIT) for i in range(4)]  # as panel_renders
    assert len(rasterized) == 4
    for i in range(4):
        monkeypatch.setattr(cache, "_last", {})
        alone = cache.view_samples(dataset, i, edge_margin=0)
        for got, want in zip(jax.tree.leaves(data.views[i]), jax.tree.leaves(alone),
                             strict=True):
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
        monkeypatch.setattr(cache, "_last", {})
        np.testing.assert_array_equal(panels[i], render_rgb(dataset, i, DEFAULT_INIT))
    assert len(rasterized) == 12


@pytest.mark.parametrize("kind", ["l1", "charbonnier", "huber"])
def test_robust_losses_match_their_formulas(kind):
    r = np.array([[-0.3, 0.0, 0.004], [0.02, -0.001, 1.5]])
    expected = {"l1": np.abs(r), "charbonnier": np.sqrt(r**2 + 1e-6) - 1e-3,
                "huber": np.where(np.abs(r) <= 0.01, 0.5 * r**2, 0.01 * (np.abs(r) - 0.005))}
    got = float(mean_rho(kind, [jnp.asarray(r)]))
    assert got == pytest.approx(expected[kind].mean(), rel=1e-6)


# ---- the step ----


@pytest.mark.parametrize("method", ["adam", "lbfgs"])
def test_step_does_not_recompile(small, method):
    spec = FitSpec()
    traces = []
    loss = make_loss(spec)

    def counted(params, data):
        traces.append(1)
        return loss(params, data)

    optimizer = make_optimizer(method)
    step = make_step(counted, optimizer)
    data = build_cache(small, DEFAULT_INIT)
    params = to_unconstrained(DEFAULT_INIT, spec)
    state = optimizer.init(params)
    brighter = dataclasses.replace(data, views=tuple(
        dataclasses.replace(v, target=v.target * 1.01) for v in data.views))
    with compiles() as counted:
        params, state, first = step(params, state, data)
        traced_once = len(traces)
        for _ in range(3):
            params, state, loss_value = step(params, state, brighter)
    # one program of make_step's jitted `step`, compiled by the first call
    assert counted.of("step") == 1 and len(traces) == traced_once
    assert float(loss_value) < float(first)


def toy_loss(params, data):
    return jnp.sum((params["x"] - data["target"]) ** 2) * data["scale"]


@pytest.mark.parametrize("optimizer", [make_optimizer(), make_optimizer("lbfgs")],
                         ids=["adam", "lbfgs"])
def test_non_finite_step_is_rejected(optimizer):
    """optax.apply_if_finite inside make_optimizer: params and the inner state unchanged,
    the rejection counted in the guard's state."""
    step = make_step(toy_loss, optimizer)
    params = {"x": jnp.array([1.0, 2.0])}
    state = optimizer.init(params)
    bad = {"target": jnp.zeros(2), "scale": jnp.asarray(jnp.nan)}
    new_params, new_state, loss = step(params, state, bad)
    assert not np.isfinite(float(loss))
    np.testing.assert_array_equal(new_params["x"], params["x"])
    for a, b in zip(jax.tree.leaves(new_state.inner_state), jax.tree.leaves(state.inner_state),
                    strict=True):
        np.testing.assert_array_equal(a, b)
    assert not bool(new_state.last_finite) and int(new_state.notfinite_count) == 1
    good = {"target": jnp.zeros(2), "scale": jnp.asarray(1.0)}
    moved, _, _ = step(params, state, good)
    assert float(jnp.sum(moved["x"] ** 2)) < 5.0


# ---- fits ----


def test_linear_fit_recovers_the_material(small):
    result = fit(small)
    assert result.method == "linear" and result.converged
    for name, err in result.errors.items():
        assert np.all(err < 1e-2), (name, err)
    assert result.warnings == ()
    assert result.loss_history[-1] <= result.loss_history[0]


def test_partial_fit_holds_the_others_fixed(small):
    spec = FitSpec(ka=None, kd="rgb", ks=None, shininess=True)
    init = ds.material(ka=TRUTH["ka"], kd=0.5, ks=TRUTH["ks"], shininess=20.0)
    result = fit(small, spec, init, with_uncertainty=False)
    np.testing.assert_array_equal(result.material.ka, init.ka)
    np.testing.assert_array_equal(result.material.ks, init.ks)
    assert set(result.errors) == {"kd", "shininess"}
    np.testing.assert_allclose(result.material.kd, TRUTH["kd"], rtol=1e-3)
    assert float(result.material.shininess) == pytest.approx(TRUTH["shininess"], rel=1e-3)


def test_lbfgs_fit_runs_and_lowers_the_loss(small):
    result = fit(small, method="lbfgs", steps=10, with_uncertainty=False)
    assert result.n_steps <= 10 and np.all(np.isfinite(result.loss_history))
    assert result.loss < 0.2 * result.loss_history[0]


def test_summary_shows_the_truth_and_counts_steps(small):
    result = fit(small, method="adam", steps=1, with_uncertainty=False)
    lines = result.summary().splitlines()
    assert "after 1 step," in lines[0] and result.n_steps == 1
    assert lines[1].split()[:3] == ["parameter", "true", "fitted"]
    row = next(line.split() for line in lines if line.startswith("kd[g] "))
    assert float(row[1]) == pytest.approx(TRUTH["kd"][1])
    # no truth in the dataset: the caller's, else no true column
    blind = dataclasses.replace(small, truth=None)
    given = fit(blind, method="adam", steps=2, truth=truth_material(), with_uncertainty=False)
    assert "after 2 steps," in given.summary() and given.errors is not None
    assert given.summary().splitlines()[1].split()[:2] == ["parameter", "true"]
    plain = fit(blind, method="adam", steps=2, with_uncertainty=False).summary()
    assert plain.splitlines()[1].split()[:2] == ["parameter", "fitted"]


def test_values_at_a_bound_have_no_standard_error(small):
    """With coefficients bounded by 0.5, kd[r] (true 0.6) ends at the bound: it is flagged,
    has no standard error anywhere, and the remaining misfit is reported."""
    result = fit(small, FitSpec(upper=0.5))
    assert "kd[r]" in result.at_bound
    true = dict(zip(value_names(result.values), np.concatenate(
        [np.ravel(TRUTH[k]) for k in ("ka", "kd", "ks", "shininess")]), strict=True))
    assert all(true[name] >= 0.45 for name in result.at_bound)  # only where the truth is
    report = result.uncertainty
    for name, std in zip(report.names, report.std_errors, strict=True):
        assert np.isnan(std) == (name in result.at_bound)
    assert result.as_dict()["std_errors"]["kd[r]"] is None
    assert "at bound" in next(line for line in result.summary().splitlines()
                              if line.startswith("kd[r] "))
    assert any("ended at a bound" in w for w in result.warnings)
    assert not result.misfit.explained
    assert any("does not explain the images" in w for w in result.warnings)


def test_a_grey_coefficient_at_a_bound_is_marked_on_each_of_its_channel_rows():
    """kd fitted grey (one value) is at a bound and ka[g] alone of the RGB ka: with a true
    material per channel the table has a row per channel, and every row of the grey kd
    says "at bound" while only ka's green row does (the rows written out by hand)."""
    values = {"ka": np.array([0.1, 0.2, 0.3]), "kd": np.array(1.0),
              "shininess": np.array(20.0)}
    truth = ds.material(ka=(0.1, 0.2, 0.3), kd=(0.9, 1.0, 0.95), ks=0.0, shininess=20.0)
    result = FitResult(material=truth, lights=(), values=values, params=values, loss=0.0,
                       loss_history=np.zeros(1), converged=True, n_steps=1, wall_time=0.0,
                       method="adam", errors=None, uncertainty=None, warnings=(),
                       at_bound=("ka[g]", "kd"))
    rows = {line.split()[0]: line.split()[1:] for line in
            result.summary(truth).splitlines()[2:]}
    assert rows == {"ka[r]": ["0.1", "0.1"], "ka[g]": ["0.2", "0.2", "at", "bound"],
                    "ka[b]": ["0.3", "0.3"], "kd[r]": ["0.9", "1", "at", "bound"],
                    "kd[g]": ["1", "1", "at", "bound"], "kd[b]": ["0.95", "1", "at", "bound"],
                    "shininess": ["20", "20"]}
    # without a truth: the grey kd is one row, at bound
    blind = {line.split()[0]: line.split()[1:]
             for line in comparison_table(result).splitlines()[2:]}
    assert blind["kd"] == ["1", "at", "bound"] and blind["ka[r]"] == ["0.1"]


def test_neighbour_differences_match_a_loop():
    rng = np.random.default_rng(0)
    height, width = 7, 9
    keep = rng.random((height, width)) > 0.3
    pixels = np.flatnonzero(keep)
    image = rng.normal(size=(height, width, 3))
    r = image.reshape(-1, 3)[pixels]
    total, count = 0.0, 0
    for y in range(height):
        for x in range(width):
            for dy, dx in ((0, 1), (1, 0)):
                if y + dy < height and x + dx < width and keep[y, x] and keep[y + dy, x + dx]:
                    total += np.sum((image[y, x] - image[y + dy, x + dx]) ** 2)
                    count += 3
    got = _neighbour_squares(r, pixels, width)
    assert got[1] == count and got[0] == pytest.approx(total, rel=1e-12)


def test_relative_errors_per_channel():
    truth = ds.material(ka=(0.2, 0.4, 0.5), kd=0.5, ks=(0.1, 0.2, 0.4), shininess=10.0)
    values = {"ka": np.array([0.22, 0.4, 0.45]), "kd": np.array(0.55), "shininess": np.array(9.0)}
    errors = relative_errors(values, truth, FitSpec(kd="grey", ks=None))
    np.testing.assert_allclose(errors["ka"], [0.1, 0.0, 0.1], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(errors["kd"], [0.1, 0.1, 0.1], rtol=1e-6, atol=1e-7)
    assert float(errors["shininess"]) == pytest.approx(0.1)


def test_fit_rejects_bad_arguments(small):
    with pytest.raises(ValueError, match="method: got 'newton'"):
        fit(small, method="newton")
    with pytest.raises(ValueError, match="loss: got 'l3'"):
        fit(small, loss="l3")
    with pytest.raises(ValueError, match="ka: got 'rg'"):
        FitSpec(ka="rg")


@pytest.mark.parametrize("settings, error, message", [
    ({"lr": -1.0}, ValueError, "lr: got -1.0; expected a positive learning rate"),
    ({"gtol": float("nan")}, ValueError, "gtol: got nan; expected a finite number >= 0"),
    ({"patience": 0}, ValueError, "patience: got 0; expected an integer >= 1"),
    ({"shininess_range": (5.0, 2.0)}, ValueError, "shininess_range: got (5.0, 2.0)"),
    ({"devices": 0}, ValueError, "devices: got 0; expected 'all' or an integer >= 1"),
    ({"devices": 4096}, ValueError, "devices: got 4096; expected at most"),
    ({"chunk": 0}, ValueError, "chunk: got 0; expected None or an integer >= 1"),
    ({"method": "lbfgs", "chunk": 2}, ValueError, "chunk: got 2; 'lbfgs' evaluates its line"),
    ({"speed": 3}, TypeError, "fit: got unknown option(s) ['speed']"),
    ({"options": "fast"}, TypeError, "options: got str; expected FitOptions"),
])
def test_fit_options_are_checked_at_the_boundary(small, settings, error, message):
    with pytest.raises(error) as info:
        fit(small, **settings)
    assert message in str(info.value)


def test_target_size_mismatch_names_the_view(small):
    views = list(small.views)
    views[1] = dataclasses.replace(views[1], target=np.zeros((40, 41, 3)))
    with pytest.raises(ValueError, match=r"views\[1\]\.target: got shape \(40, 41, 3\); "
                                         r"expected \(40, 40, 3\)"):
        dataclasses.replace(small, views=views)


# ---- the linear solver ----


def brute_force_box_qp(gram, rhs, lower, upper):
    """Every pattern of (free, at lower, at upper) per variable; the best feasible one."""
    best, best_x = np.inf, None
    for pattern in itertools.product((0, -1, 1), repeat=len(rhs)):
        pattern = np.array(pattern)
        x = np.where(pattern == -1, lower, np.where(pattern == 1, upper, 0.0))
        free = pattern == 0
        if free.any():
            sub = rhs[free] - gram[np.ix_(free, ~free)] @ x[~free]
            x[free] = np.linalg.solve(gram[np.ix_(free, free)], sub)
        if np.all(x >= lower - 1e-12) and np.all(x <= upper + 1e-12):
            value = x @ gram @ x - 2 * rhs @ x
            if value < best:
                best, best_x = value, x
    return best_x


@pytest.mark.parametrize("seed", range(6))
def test_box_least_squares_matches_enumeration(seed):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(30, 4))
    gram, rhs = a.T @ a, a.T @ rng.normal(size=30) * 3
    np.testing.assert_allclose(box_least_squares(gram, rhs, 0.0, 1.0),
                               brute_force_box_qp(gram, rhs, 0.0, 1.0), atol=1e-9)


def test_normal_equations_match_the_rendered_parts(small):
    """G and b against a design matrix built in numpy from diffshade.render_parts images."""
    spec = FitSpec(ka="grey", kd="rgb", ks=None)
    base = ds.material(ka=0.3, kd=0.5, ks=(0.2, 0.3, 0.4), shininess=20.0)
    data = build_cache(small, base)
    gram, rhs, _, _ = (np.asarray(a, np.float64)
                       for a in normal_equations(jnp.log(35.0), data, spec))
    unit = ds.material(ka=1.0, kd=1.0, ks=1.0, shininess=35.0)
    design, target = [], []
    for i, view in enumerate(small.views):
        parts = ds.render_parts(view_scene(small, i, unit), small.settings)
        pixels = np.asarray(data.views[i].pixels)
        a, d, s = (np.asarray(p, np.float64).reshape(-1, 3)[pixels]
                   for p in (parts.ambient, parts.diffuse, parts.specular))
        observed = view.target.reshape(-1, 3)[pixels].astype(np.float64)
        y = observed - s * np.asarray(base.ks)
        for c in range(3):
            usable = (observed[:, c] > 1e-6) & (observed[:, c] < 1 - 1e-6)
            columns = [a[:, c]] + [d[:, c] * (k == c) for k in range(3)]
            design.append(np.stack(columns, 1)[usable])
            target.append(y[usable, c])
    design, target = np.concatenate(design), np.concatenate(target)
    np.testing.assert_allclose(gram, design.T @ design, rtol=2e-5)
    np.testing.assert_allclose(rhs, design.T @ target, rtol=2e-5)


@pytest.mark.parametrize("spec, gains", [
    (FitSpec(), None),
    (FitSpec(ka="grey", kd="rgb", ks="grey"), None),
    (FitSpec(ka=None, kd="rgb", ks="rgb"), [[1.0, 1.0, 1.0], [0.8, 1.1, 1.3]]),
])
def test_search_profile_equals_the_general_solve(small, spec, gains):
    """The shininess search's profile (ambient and diffuse sums taken once) against the
    mean squared residual of the solve from normal_equations, at shininess on both sides
    of the truth's, with fixed coefficients and per-view gains."""
    data = build_cache(small, ds.material(ka=0.3, kd=0.5, ks=(0.2, 0.3, 0.4), shininess=20.0))
    gains = None if gains is None else np.asarray(gains)
    misfit = _fixed_profile(data, spec, gains)
    for log_shininess in np.log([3.0, 35.0, 400.0]):
        np.testing.assert_allclose(misfit(log_shininess),
                                   _solve(log_shininess, data, spec, gains)[1], rtol=1e-9,
                                   atol=1e-12)  # the truth: a residual of rounding
    assert _fixed_profile(data, FitSpec(ks=None), None) is None  # the specular part is in y


@pytest.mark.parametrize("size", [23, 24])
def test_grid_minimum_finds_the_best_grid_point_of_a_convex_profile(size):
    """Coarse to fine, on half the points and two: for every position of the minimum of a
    convex profile, the grid point a full evaluation finds best."""
    grid = np.linspace(0.0, 7.6, size)
    for centre in np.linspace(-0.5, 8.1, 173):
        taken = []

        def profile(g, centre=centre, taken=taken):
            taken.append(g)
            return (g - centre) ** 2 + 0.3 * abs(g - centre)
        best, values = _grid_minimum(profile, grid)
        assert len(taken) <= size // 2 + 3
        assert best == int(np.argmin([profile(g) for g in grid]))
        assert values[best] == profile(grid[best])


# ---- uncertainty ----


def test_standard_errors_match_central_differences():
    with jax.enable_x64(True):
        settings = ds.RenderSettings(clamp=False)
        dataset = make_dataset(SPHERE, truth_material(), n_views=2, n_lights=1, size=32,
                               settings=settings, noise_std=0.01, seed=4)
        spec = FitSpec(kd="grey")
        data = build_cache(dataset, DEFAULT_INIT)
        values = material_values(dataset.truth, spec)
        report = uncertainty(values, data, spec, warn=False)

        names = value_names(values)
        flat = np.concatenate([np.atleast_1d(np.asarray(values[k], np.float64))
                               for k in ("ka", "kd", "ks", "shininess")])

        def rendered_residuals(theta):
            mat = ds.material(ka=theta[0:3], kd=theta[3], ks=theta[4:7], shininess=theta[7])
            out = []
            for i, view in enumerate(dataset.views):
                image = np.asarray(ds.render(view_scene(dataset, i, mat), settings))
                pixels = np.asarray(data.views[i].pixels)
                out.append((image[..., :3].reshape(-1, 3)[pixels]
                            - view.target.reshape(-1, 3)[pixels]).reshape(-1))
            return np.concatenate(out)

        steps = 1e-6 * np.maximum(np.abs(flat), 1.0)
        jac = np.stack([(rendered_residuals(flat + h * e) - rendered_residuals(flat - h * e))
                        / (2 * h) for h, e in zip(steps, np.eye(len(flat)), strict=True)], 1)
        r = rendered_residuals(flat)
        sigma2 = r @ r / (len(r) - len(flat))
        expected = np.sqrt(np.diag(sigma2 * np.linalg.inv(jac.T @ jac)))
    assert names == ["ka[r]", "ka[g]", "ka[b]", "kd", "ks[r]", "ks[g]", "ks[b]", "shininess"]
    assert report.sigma2 == pytest.approx(sigma2, rel=1e-9)
    np.testing.assert_allclose(report.std_errors, expected, rtol=1e-5)
    assert report.warnings == ()


def test_rounding_bound_covers_the_error_of_8bit_targets(small):
    quantized = make_dataset(SPHERE, truth_material(), n_views=2, n_lights=1, size=40,
                             quantize_8bit=True)
    result = fit(quantized)
    report = result.uncertainty
    error = np.abs(report.values - np.concatenate(
        [np.ravel(np.asarray(TRUTH[k], np.float64)) for k in ("ka", "kd", "ks", "shininess")]))
    assert np.all(error <= report.rounding_bound)
    assert np.max(error / report.std_errors) > 5  # the rounding is not independent noise
    assert report.notes and report.notes[0].startswith("targets are 8-bit")
    assert fit(small).uncertainty.rounding_bound is None


def single_light_dataset(light_from_camera, ks):
    mat = ds.material(ka=0.3, kd=0.5, ks=ks, shininess=30.0)
    eye = np.array([0.0, 0.5, 3.0])
    camera = ds.look_at(eye, (0, 0, 0), width=32, height=32)
    direction = -eye if light_from_camera else np.array([-2.0, -0.4, -1.0])
    blank = View(camera, [ds.directional_light(direction, 0.8)], np.zeros((32, 32, 3)))
    dataset = Dataset(SPHERE, [blank], global_ambient=0.4, truth=mat)
    target = np.asarray(ds.render(view_scene(dataset, 0, mat), dataset.settings))[..., :3]
    return dataclasses.replace(dataset, views=[dataclasses.replace(blank, target=target)])


@pytest.mark.parametrize("light_from_camera, ks, expected", [
    (True, 0.4, ["ka and kd are confounded"]),
    (False, 0.0, ["ks and shininess are not determined", "shininess have no effect"]),
    (False, 0.4, []),
])
def test_identifiability_warnings(light_from_camera, ks, expected):
    dataset = single_light_dataset(light_from_camera, ks)
    spec = FitSpec()
    values = material_values(dataset.truth, spec)
    data = build_cache(dataset, DEFAULT_INIT)
    if expected:
        with pytest.warns(IdentifiabilityWarning):
            report = uncertainty(values, data, spec)
    else:
        report = uncertainty(values, data, spec)
    for start in expected:
        assert any(w.startswith(start) or start in w for w in report.warnings), report.warnings
    if not expected:
        assert report.warnings == ()
