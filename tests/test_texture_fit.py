"""Texture maps fitted with the rest: the alternation, ks maps, descent, the result files.

References are independent of the code under test:
- synthetic datasets rendered from a known procedural kd map (data_synth) or a random
  ks map, compared texel by texel and value by value with the truth, which the fit is
  never given;
- the ks map's closed form against dense least squares (jax.jacfwd of the render, the
  normal equations solved by numpy) in float64;
- Adam and L-BFGS against the conjugate-gradient solution of the same problem;
- `diffshade render --material OUT/result.json` against a render built by hand from
  result.json's numbers and the map's .npy file.
"""

import dataclasses
import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_textures import grid_laplacian

import diffshade as ds
import fitting
from data_synth import make_dataset
from diffshade.cli import main
from fitting.data.folder import save_dataset
from fitting.solve import solve_texture

# ------------------------------------------------------------ joint fit (Python)


@pytest.fixture(scope="module")
def kd_dataset():
    """A textured sphere (an 8 x 8 procedural kd), 3 cameras x 2 lights, light noise."""
    return make_dataset("icosphere", n_views=3, n_lights=2, size=24, texture=8, seed=3,
                        noise_std=0.003)


@pytest.mark.cost(40)
def test_the_kd_map_and_the_uniform_values_come_back_without_the_truth(kd_dataset):
    truth = kd_dataset.truth
    blind = dataclasses.replace(kd_dataset, truth=None)
    result = fitting.fit(blind, textures={"kd": 8})
    assert result.truth is None and result.errors is None  # nothing read from a truth
    assert set(result.values) == {"ka", "ks", "shininess"}
    assert 1 <= len(result.rounds) <= 10 and result.status == "converged"
    assert result.rounds[-1]["change"] <= 1e-3
    # the uniform values: within 2% of the truth
    for name in ("ka", "ks", "shininess"):
        true = np.asarray(getattr(truth, name), np.float64)
        np.testing.assert_allclose(result.values[name], true, rtol=0.02, err_msg=name)
    assert np.all(np.isfinite(result.uncertainty.std_errors))
    solution = result.textures["kd"]
    coverage, std_error = np.asarray(solution.coverage), np.asarray(solution.std_error)
    kd = np.asarray(solution.texels)
    well_seen = coverage >= 2
    assert well_seen.sum() >= 12
    error = kd[well_seen] - np.asarray(truth.kd.texels)[well_seen]
    assert np.sqrt(np.mean((error / std_error[well_seen]) ** 2)) < 3
    assert np.all(np.isnan(kd[coverage == 0]))  # unseen: reported, not invented


@pytest.mark.cost(30)
def test_kd_and_ks_maps_converge_like_a_kd_map(kd_dataset):
    """Both maps from one system per shininess: the rounds converge (they ran out at 10
    when the maps took turns), to the truth's shininess and ka."""
    truth = kd_dataset.truth
    result = fitting.fit(dataclasses.replace(kd_dataset, truth=None),
                         textures={"kd": 8, "ks": 8})
    assert result.status == "converged" and len(result.rounds) <= 6
    assert set(result.values) == {"ka", "shininess"}
    np.testing.assert_allclose(result.values["shininess"], truth.shininess, rtol=0.03)
    np.testing.assert_allclose(result.values["ka"], truth.ka, rtol=0.03)
    kd = result.textures["kd"]
    well_seen = np.asarray(kd.coverage) >= 2
    error = np.asarray(kd.texels)[well_seen] - np.asarray(truth.kd.texels)[well_seen]
    # under so broad a highlight (shininess about 4) a ks texel looks much like a kd
    # texel: the maps trade off, and the kd map is a few hundredths off (0.05 here)
    assert np.sqrt(np.mean(error ** 2)) < 0.08


def test_the_rounds_shininess_jumps_to_the_limit_of_a_geometric_sequence():
    from fitting.texture_run import MAX_LOG_STEP, _extrapolated

    material = ds.material(kd=0.5, shininess=1.0)
    limit, step, ratio = np.log(40.0), 0.3, 0.6
    logs = [limit - step / (1 - ratio) * ratio ** k for k in range(3)]
    carried = logs[:2]
    jumped, carried = _extrapolated(ds.replace(material, shininess=np.exp(logs[2])), carried)
    np.testing.assert_allclose(jumped.shininess, 40.0, rtol=1e-6)
    assert len(carried) == 1  # two plain rounds before the next jump
    # steps that do not shrink (ratio >= MAX_RATIO, or a sign change) are not extrapolated
    for third in (logs[1] + 1.2 * (logs[1] - logs[0]), logs[1] - 0.5 * (logs[1] - logs[0])):
        kept, carried = _extrapolated(ds.replace(material, shininess=np.exp(third)), logs[:2])
        np.testing.assert_allclose(kept.shininess, np.exp(third), rtol=1e-6)
        assert len(carried) == 2
    # a slow sequence: the jump is capped at MAX_LOG_STEP
    slow = [0.0, 0.1, 0.19]
    capped, _ = _extrapolated(ds.replace(material, shininess=np.exp(slow[2])), slow[:2])
    np.testing.assert_allclose(np.log(capped.shininess), 0.19 + MAX_LOG_STEP, rtol=1e-6)


def dense_marginal_std_errors(dataset, result):
    """(with the map marginalised, with it held) standard errors of ka, ks, shininess: the
    dense Jacobian of the unclamped render in the kd texels and those values at the fit,
    over the pixels the fit counts, the map's prior (its lam and the solve's ridge on
    unseen texels) on the texels' block, sigma^2 over n less every unknown."""
    from fitting.model.cache import build_cache
    from fitting.texture_run import _counted_masks

    kd = result.textures["kd"]
    res = kd.texels.shape[0]
    masks = _counted_masks(dataset, build_cache(dataset, result.material, uv=True))
    settings = ds.replace(dataset.settings, clamp=False)
    at = (jnp.nan_to_num(jnp.asarray(kd.texels)), *(jnp.asarray(result.values[n])
                                                   for n in ("ka", "ks", "shininess")))
    rows, residuals = [], []
    for i, mask in enumerate(masks):
        def view(texels, ka, ks, shininess, i=i):
            material = ds.replace(result.material, kd=ds.replace(result.material.kd,
                                                                   texels=texels), ka=ka, ks=ks,
                                  shininess=shininess)
            return ds.render(fitting.view_scene(dataset, i, material), settings)[..., :3]
        jac = jax.jit(jax.jacfwd(view, argnums=(0, 1, 2, 3)))(*at)
        keep = np.repeat(mask.reshape(-1), 3)
        rows.append(np.concatenate([np.asarray(j, np.float64).reshape(keep.size, -1)
                                    for j in jac], 1)[keep])
        residuals.append((np.asarray(view(*at)) - dataset.views[i].target).reshape(-1)[keep])
    jac, residuals = np.concatenate(rows), np.concatenate(residuals)
    texels = res * res * 3
    normal = jac.T @ jac
    unseen = np.repeat((np.asarray(kd.coverage) == 0).reshape(-1), 3)
    mean_weight = normal[:texels, :texels].sum(1).mean()
    normal[:texels, :texels] += (kd.lam * np.kron(grid_laplacian(res), np.eye(3))
                                 + np.diag(np.where(unseen, 1e-6 * mean_weight, 0.0)))
    p = jac.shape[1] - texels
    rss = float(residuals @ residuals)
    marginal = rss / (residuals.size - p - np.sum(~unseen)) * np.linalg.inv(normal)
    held = rss / (residuals.size - p) * np.linalg.inv(normal[texels:, texels:])
    return np.sqrt(np.diag(marginal)[texels:]), np.sqrt(np.diag(held))


@pytest.mark.cost(40)
def test_the_uniform_standard_errors_marginalise_the_map(kd_dataset):
    """ka, ks and shininess fitted beside a kd map: their standard errors are the dense
    joint covariance's (the map's texels marginalised), above those with the map held."""
    result = fitting.fit(dataclasses.replace(kd_dataset, truth=None), textures={"kd": 8})
    report = result.uncertainty
    assert report.names == ("ka[r]", "ka[g]", "ka[b]", "ks[r]", "ks[g]", "ks[b]",
                            "shininess")
    marginal, held = dense_marginal_std_errors(kd_dataset, result)
    np.testing.assert_allclose(report.gauss_newton_std_errors, marginal, rtol=0.02)
    # the map's texels take up part of what ks and the shininess explain: their errors
    # grow most (about 3.6x and 1.9x here), ka's little (the unlit side pins it)
    assert np.all(marginal >= held)
    assert np.all(marginal[3:] > 1.5 * held[3:])


@pytest.mark.cost(15)
@pytest.mark.cost(10)
def test_a_map_alone_holds_the_rest_at_the_start(kd_dataset):
    truth = kd_dataset.truth
    start = ds.material(ka=truth.ka, kd=0.5, ks=truth.ks, shininess=truth.shininess)
    nothing = fitting.FitSpec(ka=None, kd=None, ks=None, shininess=False)
    result = fitting.fit(dataclasses.replace(kd_dataset, truth=None), nothing, start,
                         textures={"kd": 8})
    assert result.values == {} and len(result.rounds) == 1 and result.status == "converged"
    for name in ("ka", "ks", "shininess"):
        np.testing.assert_array_equal(getattr(result.material, name), getattr(start, name))
    solution = result.textures["kd"]
    well_seen = np.asarray(solution.coverage) >= 2
    error = np.asarray(solution.texels)[well_seen] - np.asarray(truth.kd.texels)[well_seen]
    assert np.sqrt(np.mean((error / np.asarray(solution.std_error)[well_seen]) ** 2)) < 3


def test_the_cache_reads_a_held_map_as_render_does_and_the_closed_form_holds_it():
    from fitting.model.cache import build_cache, predict
    from fitting.solve.linear import solve_linear

    data = make_dataset("icosphere", n_views=2, n_lights=2, size=16, texture=8, seed=2)
    cache = build_cache(data, data.truth)  # the truth's kd map, held
    assert all(v.uv is not None for v in cache.views)
    for i, samples in enumerate(cache.views):
        scene = fitting.view_scene(data, i, data.truth)
        image = np.asarray(ds.render(scene, data.settings))[..., :3].reshape(-1, 3)
        got = predict(data.truth, cache.lights[i], cache.global_ambient, samples,
                      data.settings)
        np.testing.assert_allclose(got, image[np.asarray(samples.pixels)], atol=2e-6)
    # noiseless: the closed form recovers ka, ks and shininess around the held map
    values = solve_linear(cache, fitting.FitSpec(kd=None))
    for name in ("ka", "ks", "shininess"):
        np.testing.assert_allclose(values[name], getattr(data.truth, name), rtol=2e-3,
                                   err_msg=name)


def test_the_caches_texture_lookup_follows_the_kernels_setting():
    """The cache's shading reads the map with the host texture op only where the settings
    choose the host kernels (a fresh install's first runs choose 'jax' while numba
    compiles them: diffshade.host.warmup), and both read the same values."""
    from fitting.model.cache import build_cache, predict

    data = make_dataset("icosphere", n_views=1, n_lights=1, size=12, texture=4, seed=1)
    cache = build_cache(data, data.truth)
    samples, lights = cache.views[0], cache.lights[0]
    values = {}
    for kernels in ("jax", "host"):
        settings = dataclasses.replace(data.settings, kernels=kernels)
        fn = functools.partial(predict, lights=lights, global_ambient=cache.global_ambient,
                               samples=samples, settings=settings)
        program = str(jax.make_jaxpr(fn)(data.truth))
        assert ("sample_texture_op" in program) == (kernels == "host"), kernels
        values[kernels] = np.asarray(fn(data.truth))
    np.testing.assert_allclose(values["jax"], values["host"], atol=1e-6)


# ------------------------------------------------------------------- the ks map


def sphere_views(material, azimuths, size=16):
    """Views of a textured sphere with `material`, one light near each camera, their
    unclamped renders as targets and covered pixels as masks."""
    mesh = ds.icosphere(2, uv=True)
    scenes, targets, masks = [], [], []
    for azimuth in np.radians(azimuths):
        eye = np.array([3 * np.sin(azimuth), 0.8, 3 * np.cos(azimuth)])
        cam = ds.look_at(eye, (0, 0, 0), width=size, height=size)
        light = ds.directional_light(-(eye + np.array([0.5, 1.0, 0.0])), 0.9)
        scene = ds.make_scene(mesh, cam, [light], material)
        image = ds.render(scene, ds.RenderSettings(clamp=False))
        scenes.append(scene)
        targets.append(image[..., :3])
        masks.append(image[..., 3] > 0.5)
    return scenes, targets, masks


@pytest.mark.cost(30)
def test_the_ks_map_in_closed_form_is_dense_least_squares(x64):
    res = 3
    truth = ds.texture(np.random.default_rng(4).uniform(0.2, 0.8, (res, res, 3)))
    scenes, targets, masks = sphere_views(ds.material(ka=0.2, kd=0.4, ks=truth, shininess=8.0),
                                          [0.0, 120.0, 240.0])
    noisy = [t + 0.01 * np.random.default_rng(i).normal(size=t.shape)
             for i, t in enumerate(targets)]
    solved = solve_texture(scenes, noisy, masks, res, field="ks", smoothness=0.1, tol=1e-13)
    normal, rhs = np.zeros((res * res * 3,) * 2), np.zeros(res * res * 3)
    zero = jnp.zeros((res, res, 3))
    for scene, target, mask in zip(scenes, noisy, masks, strict=True):
        def view(t, s=scene):
            material = ds.replace(s.material, ks=ds.replace(s.material.ks, texels=t))
            return ds.render(ds.replace(s, material=material),
                             ds.RenderSettings(clamp=False))[..., :3]
        a = np.asarray(jax.jit(jax.jacfwd(view))(zero)).reshape(-1, res * res * 3)
        keep = np.repeat(np.asarray(mask).reshape(-1), 3)
        normal += a[keep].T @ a[keep]
        rhs += a[keep].T @ (np.asarray(target) - np.asarray(view(zero))).reshape(-1)[keep]
    weight = normal.sum(1)
    seen = weight.reshape(res, res, 3).max(-1) > 1e-9 * weight.mean()
    assert seen.all()  # every texel of so coarse a map is near some highlight
    lam = 0.1 * weight.mean()
    lap = grid_laplacian(res)
    want = np.linalg.solve(normal + lam * np.kron(lap, np.eye(3)), rhs).reshape(res, res, 3)
    np.testing.assert_allclose(solved.lam, lam, rtol=1e-9)
    np.testing.assert_allclose(solved.texels, want, atol=1e-8)
    # noiseless and without the prior: the truth itself
    exact = solve_texture(scenes, targets, masks, res, field="ks", smoothness=0.0, tol=1e-13)
    np.testing.assert_allclose(exact.texels, truth.texels, atol=1e-6)


# ------------------------------------------- kd and ks maps and ka: one system


def dense_columns(scenes, targets, masks, res, settings):
    """(the columns [N, p] of the kd texels, the ks texels and ka (3), the targets less
    the render with all of them at 0 [N]) over the counted pixel-channels, by jacfwd."""
    columns, residuals = [], []
    zero = (jnp.zeros((res, res, 3)), jnp.zeros((res, res, 3)), jnp.zeros(3))
    for scene, target, mask in zip(scenes, targets, masks, strict=True):
        def view(kd, ks, ka, s=scene):
            material = ds.replace(s.material, kd=ds.replace(s.material.kd, texels=kd),
                                  ks=ds.replace(s.material.ks, texels=ks), ka=ka)
            return ds.render(ds.replace(s, material=material), settings)[..., :3]
        jac = jax.jit(jax.jacfwd(view, argnums=(0, 1, 2)))(*zero)
        keep = np.repeat(np.asarray(mask).reshape(-1), 3)
        n = keep.size
        columns.append(np.concatenate([np.asarray(j).reshape(n, -1) for j in jac], 1)[keep])
        residuals.append((np.asarray(target) - np.asarray(view(*zero))).reshape(-1)[keep])
    return np.concatenate(columns), np.concatenate(residuals)


@pytest.mark.cost(40)
def test_kd_and_ks_maps_and_ka_are_one_least_squares_solution(x64):
    """Both maps and the uniform ka from one solve: the dense regularized least squares
    over all their unknowns at once; the texels' share of ka's normal matrix is the
    Schur complement's (ka's block of the dense inverse)."""
    from fitting.solve.texture_joint import solve_texture_jointly

    res, smoothness = 3, 0.05
    rng = np.random.default_rng(8)
    kd, ks = (ds.texture(rng.uniform(0.2, 0.7, (res, res, 3))) for _ in range(2))
    scenes, targets, masks = sphere_views(
        ds.material(ka=(0.2, 0.25, 0.15), kd=kd, ks=ks, shininess=8.0),
        [0.0, 90.0, 180.0, 270.0])
    noisy = [t + 0.01 * np.random.default_rng(i).normal(size=t.shape)
             for i, t in enumerate(targets)]
    settings = ds.RenderSettings(clamp=False)
    joint = solve_texture_jointly(scenes, noisy, masks, {"kd": res, "ks": res}, settings,
                                  coefficients=["ka"], smoothness=smoothness, tol=1e-13)
    a, y = dense_columns(scenes, noisy, masks, res, settings)
    normal = a.T @ a
    texels = res * res * 3
    lap = np.kron(grid_laplacian(res), np.eye(3))
    prior, lam = np.zeros_like(normal), []
    for block in range(2):  # each map's weight: smoothness x its own mean data weight
        span = slice(block * texels, (block + 1) * texels)
        lam.append(smoothness * normal[span, span].sum(1).mean())
        prior[span, span] = lam[-1] * lap
    want = np.linalg.solve(normal + prior, a.T @ y)
    assert np.all((want[-3:] > 0) & (want[-3:] < 1))  # inside the box: the free optimum
    np.testing.assert_allclose(joint.maps["kd"].texels, want[:texels].reshape(res, res, 3),
                               atol=1e-7)
    np.testing.assert_allclose(joint.maps["ks"].texels,
                               want[texels:2 * texels].reshape(res, res, 3), atol=1e-7)
    np.testing.assert_allclose(joint.values["ka"], want[-3:], atol=1e-8)
    np.testing.assert_allclose([joint.maps["kd"].lam, joint.maps["ks"].lam], lam, rtol=1e-9)
    # ka's marginal: P'P less the texels' share is the inverse of ka's block of the inverse
    schur = np.diag(normal[-3:, -3:]) - joint.eliminated[("ka", "ka")]
    marginal = np.linalg.inv(normal + prior)[-3:, -3:]
    np.testing.assert_allclose(1.0 / schur, np.diag(marginal), rtol=1e-6)
    np.testing.assert_allclose(marginal - np.diag(np.diag(marginal)), 0.0, atol=1e-12)


# --------------------------------------------------------- Adam and L-BFGS on texels


@pytest.mark.cost(25)
@pytest.mark.parametrize("method", ["adam", "lbfgs"])
def test_descent_on_the_texels_reaches_the_closed_form(method, x64):
    res = 4
    truth = ds.texture(np.random.default_rng(5).uniform(0.2, 0.7, (res, res, 3)))
    scenes, targets, masks = sphere_views(ds.material(ka=0.2, kd=truth, ks=0.3, shininess=8.0),
                                          [0.0, 120.0, 240.0])
    noisy = [t + 0.01 * np.random.default_rng(i).normal(size=t.shape)
             for i, t in enumerate(targets)]
    closed = solve_texture(scenes, noisy, masks, res, smoothness=0.01, tol=1e-10)
    descended = solve_texture(scenes, noisy, masks, res, smoothness=0.01, method=method,
                              tol=1e-6)
    assert descended.iterations > 1 and descended.residual <= 1e-6
    np.testing.assert_allclose(descended.lam, closed.lam, rtol=1e-12)
    np.testing.assert_allclose(descended.texels, closed.texels, atol=1e-4)
    np.testing.assert_array_equal(descended.coverage, closed.coverage)


# ------------------------------------------------------- the command and its files


@pytest.fixture(scope="module")
def kd_folder(tmp_path_factory, kd_dataset):
    folder = tmp_path_factory.mktemp("texture") / "set"
    save_dataset(kd_dataset, folder)
    return folder


@pytest.mark.cost(30)
def test_fit_texture_writes_the_standard_result_that_render_reads(kd_folder, tmp_path,
                                                                  capsys):
    out = tmp_path / "out"
    assert main(["fit", str(kd_folder), "-o", str(out), "--texture", "kd=8",
                 "--smoothness", "0.01"]) == 0
    printed = capsys.readouterr().out
    assert "kd map 8x8" in printed and "rounds" in printed
    result = json.loads((out / "result.json").read_text())
    assert result["format"] == "diffshade-fit-result"
    entry = result["textures"]["kd"]
    assert {k: entry[k] for k in ("png", "npy", "coverage", "std_error")} == {
        "png": "kd.png", "npy": "kd.npy", "coverage": "kd_coverage.npy",
        "std_error": "kd_std_error.npy"}
    assert entry["smoothness"] == 0.01 and entry["resolution"] == 8
    assert result["material"]["kd"] == {"texture": "kd.png"}
    assert set(result["values"]) == {"ka", "ks", "shininess"} and result["rounds"]
    assert result["truth"]["kd"]["texture"].endswith("truth.kd.npy")  # compared, not read
    for name in ("kd.npy", "kd_coverage.npy", "kd_std_error.npy", "kd.png", "view_000.png"):
        assert (out / name).is_file()
    mtl = (out / "material.mtl").read_text().splitlines()
    assert "map_Kd kd.png" in mtl and "Kd 1.000000 1.000000 1.000000" in mtl
    # render --material OUT/result.json: the recovered map, as built by hand from the files
    assert main(["render", str(kd_folder / "view_000.json"), "--material",
                 str(out / "result.json"), "-o", str(tmp_path / "with_map.npy")]) == 0
    rendered = np.load(tmp_path / "with_map.npy")[..., :3]
    values = result["values"]
    kd = np.clip(np.nan_to_num(np.load(out / "kd.npy"), nan=0.0), 0.0, 1.0)
    scene, settings = ds.load_scene(kd_folder / "view_000.json")
    by_hand = ds.material(ka=values["ka"], kd=ds.texture(kd), ks=values["ks"],
                          shininess=values["shininess"])
    want = np.asarray(ds.render(ds.replace(scene, material=by_hand), settings))[..., :3]
    np.testing.assert_allclose(rendered, want, atol=3e-3)  # kd.png: 8 bits
    flat = ds.material(ka=values["ka"], kd=np.nanmean(kd, (0, 1)), ks=values["ks"],
                       shininess=values["shininess"])
    uniform = np.asarray(ds.render(ds.replace(scene, material=flat), settings))[..., :3]
    assert np.max(np.abs(rendered - uniform)) > 0.05  # the map is used, not its mean


def test_fit_with_maps_refuses_bad_input_with_one_line(kd_folder, tmp_path, capsys,
                                                       monkeypatch):
    plain = tmp_path / "plain"
    save_dataset(make_dataset("icosphere", n_views=1, n_lights=1, size=12), plain)
    cases = [
        ([str(kd_folder), "--texture", "kd=0"], "--texture: got 'kd=0'"),
        ([str(kd_folder), "--texture", "xs=4"], "--texture: got 'xs=4'"),
        ([str(kd_folder), "--texture", "kd=4,kd=8"], "--texture: got 'kd=4,kd=8'"),
        ([str(plain), "--texture", "ks=4"], "--texture: ks=4: the dataset's mesh has no UVs"),
        ([str(kd_folder), "--texture", "kd=4", "--grey", "kd"],
         "--grey: got 'kd'; kd is recovered as a map"),
        ([str(kd_folder), "--texture", "kd=4", "--fit", "ka,light_colors"],
         "--fit: got 'ka,light_colors'; with --texture expected names among"),
        ([str(kd_folder), "--texture", "kd=4", "--resume"], "--resume: given with --texture"),
        ([str(kd_folder), "--texture", "kd=4", "--holdout", "1"],
         "--holdout: given with --texture"),
        ([str(kd_folder), "--smoothness", "0.1"], "--smoothness: given without --texture"),
        ([str(kd_folder), "--texture", "kd=4", "--smoothness", "-1"],
         "--smoothness: got -1.0"),
        ([str(kd_folder), "--texture", "kd=4", "--method", "newton"], "--method"),
    ]
    for args, words in cases:
        assert main(["fit", *args, "-o", str(tmp_path / "bad")]) == 2, args
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], (args, err)
        assert not (tmp_path / "bad").exists()
    # beyond memory: the map's solve against the budget (diffshade.budget)
    monkeypatch.setenv("DIFFSHADE_MEMORY_LIMIT", "600M")
    assert main(["fit", str(kd_folder), "-o", str(tmp_path / "bad"), "--texture",
                 "kd=4096"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--texture: got kd=4096; a 4096x4096 kd map" in err[0], err
    assert "DIFFSHADE_MEMORY_LIMIT" in err[0]
    assert not (tmp_path / "bad").exists()


def test_fit_with_maps_in_python_names_the_bad_argument(kd_dataset):
    plain = make_dataset("icosphere", n_views=1, n_lights=1, size=12)
    for dataset, kwargs, words in [
            (kd_dataset, {"textures": {"kd": 0}}, "textures: got kd=0"),
            (kd_dataset, {"textures": {"albedo": 8}}, "textures: got a map named 'albedo'"),
            (kd_dataset, {"textures": "kd=8"}, "textures: got 'kd=8'"),
            (plain, {"textures": {"kd": 8}}, "textures: kd=8: the dataset's mesh has no UVs"),
            (kd_dataset, {"smoothness": 0.1}, "smoothness: got 0.1 without textures"),
            (kd_dataset, {"textures": {"kd": 8}, "spec": fitting.FitSpec(light_colors=True)},
             "spec: fits light_colors with textures")]:
        with pytest.raises(ValueError, match=words):
            fitting.fit(dataset, **kwargs)
