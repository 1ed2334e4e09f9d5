"""Tests for the command line (diffshade.cli) and the atomic writers it uses (diffshade.io.images).

References: the same scenes rendered through the API and quantized with numpy, PNG
bytes decoded by imageio directly, and the files left in the output folder after a
failure (there must be none)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

import diffshade as ds
import diffshade.io.images as dio
from diffshade import cli
from diffshade.scene.builtin import BUILTIN_SCENES, builtin_scene


def quantized(rgb):
    """Linear rgb as an 8-bit sRGB PNG stores it, decoded back to linear."""
    codes = np.round(ds.linear_to_srgb(np.clip(np.asarray(rgb, np.float64), 0.0, 1.0)) * 255)
    return ds.srgb_to_linear(codes / 255.0)


def one_error_line(capsys):
    out, err = capsys.readouterr()
    assert out == ""
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("diffshade: error: "), err
    return lines[0]


# ---- render ----


def test_render_builtin_writes_the_api_image(tmp_path, capsys):
    out = tmp_path / "new" / "box.png"
    assert cli.main(["render", "--builtin", "box", "-o", str(out), "--size", "24x16"]) == 0
    assert capsys.readouterr().out == f"{out}\n"
    want = np.asarray(ds.render(builtin_scene("box", 24, 16)))[..., :3]
    got = dio.read_image(out)
    assert got.shape == (16, 24, 3)
    np.testing.assert_allclose(got, quantized(want), atol=1e-6)


SCENE = {
    "mesh": {"builtin": {"icosphere": {"subdivisions": 1}}},
    "camera": {"eye": [0, 0, 3], "target": [0, 0, 0], "width": 40, "height": 40},
    "lights": [{"type": "point", "position": [1, 2, 3], "color": 0.9}],
    "material": {"kd": [0.8, 0.3, 0.2], "ks": 0.5, "shininess": 20, "emission": 0.1},
    "background": 0.25,
}


def scene_by_api(width, height):
    camera = ds.look_at((0, 0, 3), (0, 0, 0), width=width, height=height)
    mat = ds.material(kd=(0.8, 0.3, 0.2), ks=0.5, shininess=20, emission=0.1)
    return ds.make_scene(ds.icosphere(1), camera, [ds.point_light((1, 2, 3), 0.9)], mat,
                         background=0.25)


def test_render_scene_file_to_npy_with_parts_shading_and_size(tmp_path, capsys):
    scene_path = tmp_path / "scene.json"
    scene_path.write_text(json.dumps(SCENE))
    out = tmp_path / "img.npy"
    argv = ["render", str(scene_path), "-o", str(out), "--parts", "--shading", "flat",
            "--size", "20x12"]
    assert cli.main(argv) == 0
    names = ["img.npy"] + [f"img_{part}.npy" for part in ("ambient", "diffuse", "specular",
                                                         "emission")]
    assert capsys.readouterr().out.split() == [str(tmp_path / name) for name in names]
    scene, settings = scene_by_api(20, 12), ds.RenderSettings(shading="flat")
    rgba = np.load(out)
    assert rgba.dtype == np.float32 and rgba.shape == (12, 20, 4)
    np.testing.assert_allclose(rgba, ds.render(scene, settings), atol=1e-6)
    parts = ds.render_parts(scene, settings)
    for part in ("ambient", "diffuse", "specular", "emission"):
        np.testing.assert_allclose(np.load(tmp_path / f"img_{part}.npy"),
                                   getattr(parts, part), atol=1e-6)


def bad_scene(tmp_path):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({**SCENE, "lights": [{"type": "spot", "position": [0, 0, 3],
                                                     "direction": [0, 0, -1], "cutoff": 120}]}))
    return str(path)


def bad_json(tmp_path):
    path = tmp_path / "broken.json"
    path.write_text('{"mesh": {}\n "camera": {}}')
    return str(path)


@pytest.mark.parametrize("argv, message", [
    (lambda t: ["render", bad_scene(t), "-o", f"{t}/x.png"],
     "bad.json: lights[0].cutoff: got 120; expected degrees in [0, 90], or 180"),
    (lambda t: ["render", bad_json(t), "-o", f"{t}/x.png"],
     "broken.json: line 2, column 2: invalid JSON"),
    (lambda t: ["render", f"{t}/missing.json", "-o", f"{t}/x.png"],
     "scene file not found: '{t}/missing.json'"),
    (lambda t: ["render", "--builtin", "cube", "-o", f"{t}/x.png"],
     "argument --builtin: invalid choice: 'cube'"),
    (lambda t: ["render", "--builtin", "box", "-o", f"{t}/x.png", "--size", "32"],
     "argument --size: got '32'; expected WxH"),
    (lambda t: ["render", bad_scene(t), "--builtin", "box", "-o", f"{t}/x.png"],
     "render: expected a scene file or --builtin NAME, not both"),
    (lambda t: ["render", "--builtin", "box", "-o", f"{t}/x.jpg"],
     "--output: got '{t}/x.jpg'; expected a path ending in .png or .npy"),
    (lambda t: [], "the following arguments are required: COMMAND"),
])
def test_user_errors_print_one_line_and_write_nothing(tmp_path, capsys, argv, message):
    before = set(os.listdir(tmp_path))
    assert cli.main(argv(tmp_path)) == 2
    line = one_error_line(capsys)
    assert message.format(t=tmp_path) in line
    assert set(os.listdir(tmp_path)) - before <= {"bad.json", "broken.json"}


def test_unwritable_output_is_a_user_error_and_leaves_no_temporary(tmp_path, capsys):
    (tmp_path / "taken.png").mkdir()
    # The size of the test above: the render is compiled once for both.
    argv = ["render", "--builtin", "box", "-o", str(tmp_path / "taken.png"), "--size", "24x16"]
    assert cli.main(argv) == 2
    assert str(tmp_path / "taken.png") in one_error_line(capsys)
    assert os.listdir(tmp_path) == ["taken.png"] and os.listdir(tmp_path / "taken.png") == []


def test_help_returns_zero(capsys):
    assert cli.main(["render", "--help"]) == 0
    assert "--builtin" in capsys.readouterr().out


def test_builtin_names_are_listed_in_the_error():
    with pytest.raises(ValueError, match="'sphere', 'torus', 'box'"):
        builtin_scene("cube")
    assert BUILTIN_SCENES == ("sphere", "torus", "box")


def diffshade_script():
    return str(Path(sys.executable).with_name("diffshade"))


def test_console_script_renders_and_fails_cleanly(tmp_path):
    out = tmp_path / "x.png"
    argv = [diffshade_script(), "render", "--builtin", "sphere", "-o", str(out),
            "--size", "32x32"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout == f"{out}\n"
    assert iio.imread(out).shape == (32, 32, 3)

    bad_out = tmp_path / "bad.png"
    argv = [diffshade_script(), "render", bad_scene(tmp_path), "-o", str(bad_out)]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2
    assert "Traceback" not in done.stderr
    assert done.stderr.splitlines() == [
        f"diffshade: error: {tmp_path}/bad.json: lights[0].cutoff: got 120; expected degrees "
        "in [0, 90], or 180 (no cone)"]
    assert not bad_out.exists()


# ---- the command table ----


def hello_command(subparsers):
    parser = subparsers.add_parser("hello")
    parser.add_argument("name")
    parser.set_defaults(run=lambda args: print("hello", args.name) or 7)


def test_commands_are_render_and_the_installed_entry_points():
    from data_synth.cli import register as register_synth
    from fitting.cli import register as register_fit
    from fitting.import_cli import register as register_import
    # an entry point added to pyproject.toml needs `pip install -e .` to be installed
    assert list(cli.COMMANDS) == ["render", "fit", "import", "synth"]
    assert cli.COMMANDS["render"] is cli._register_render
    loaded = {name: cli.COMMANDS[name].entry_point.load() for name in ("fit", "import", "synth")}
    assert loaded == {"fit": register_fit, "import": register_import, "synth": register_synth}


def test_a_command_registers_only_its_own_parser():
    """`diffshade render` imports none of the applications (fitting, optax, SciPy), which
    take a fresh process about as long to import as diffshade itself."""
    code = ("import sys; from diffshade import cli; "
            "names = lambda p: sorted(p._subparsers._group_actions[0].choices); "
            "print(names(cli.build_parser('render')), "
            "sorted(m for m in ('fitting', 'data_synth', 'optax', 'scipy.optimize') "
            "if m in sys.modules), names(cli.build_parser('nothing')), "
            "names(cli.build_parser()))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True, timeout=300)
    every = sorted(cli.COMMANDS)
    assert done.stdout.strip() == f"{['render']} [] {every} {every}"


def test_synth_imports_no_solver_and_a_render_no_scipy():
    """`diffshade synth` imports the dataset format, not the fit's solvers and reports
    (fitting's floors load on first use), and lowering a render on the JAX kernels (a
    fresh install's first runs) imports no SciPy (the normals' inverse transpose is not
    LAPACK's): each takes a fresh process a tenth of a second or more."""
    code = ("import sys, jax; from diffshade import cli; cli.build_parser('synth'); "
            "import diffshade as ds; "
            "jax.jit(ds.render).lower(ds.builtin_scene('sphere', 16, 16)); "
            "print(sorted(m for m in ('optax', 'fitting.solve', 'fitting.report', "
            "'scipy.linalg', 'scipy.optimize') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True, timeout=300, env=os.environ | {"DIFFSHADE_KERNELS": "jax"})
    assert done.stdout.strip() == "[]"


def test_a_command_in_the_table_is_dispatched(monkeypatch, capsys):
    monkeypatch.setitem(cli.COMMANDS, "hello", hello_command)
    assert cli.main(["hello", "world"]) == 7
    assert capsys.readouterr().out == "hello world\n"


# ---- io ----


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_write_png_quantizes_and_read_image_scales_back(tmp_path, channels):
    """Linear PNGs here; sRGB encoding is tested in tests/test_color.py."""
    values = np.array([-0.2, 0.0, 0.3, 0.499, 0.501, 0.9999, 1.0, 1.7])
    image = np.resize(values, (3, 5, channels))
    path = dio.write_png(tmp_path / "a.png", image, color_space="linear")
    stored = iio.imread(path)
    want = np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)
    np.testing.assert_array_equal(stored, want[..., 0] if channels == 1 else want)
    np.testing.assert_allclose(dio.read_image(path), want / 255.0, rtol=1e-6)


def test_npy_round_trip_is_exact(tmp_path):
    image = np.random.default_rng(0).normal(size=(4, 3, 4)).astype(np.float32)
    got = dio.read_image(dio.write_npy(tmp_path / "a.npy", image))
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, image)


def test_write_json_keeps_vectors_on_one_line(tmp_path):
    obj = {"eye": [0, 0.1, 3], "m": [[1, 0], [0, 1]], "none": None, "s": "x"}
    text = Path(dio.write_json(tmp_path / "a.json", obj)).read_text()
    assert json.loads(text) == obj
    assert '"eye": [0, 0.1, 3],' in text and "    [1, 0],\n" in text
    with pytest.raises(ValueError, match="a.json"):
        dio.write_json(tmp_path / "a.json", {"x": float("nan")})
    assert json.loads((tmp_path / "a.json").read_text()) == obj


def test_write_text_and_permissions_follow_the_umask(tmp_path):
    old = os.umask(0o027)
    try:
        path = dio.write_text(tmp_path / "a.txt", "héllo\n")
    finally:
        os.umask(old)
    assert Path(path).read_text(encoding="utf-8") == "héllo\n"
    assert os.stat(path).st_mode & 0o777 == 0o640


@pytest.mark.parametrize("fails", ["replace", "fsync"])
@pytest.mark.parametrize("existing", [False, True])
def test_failed_write_leaves_no_partial_file(tmp_path, monkeypatch, fails, existing):
    target = tmp_path / "out.png"
    if existing:
        target.write_bytes(b"old")

    def broken(*args):
        raise OSError(f"simulated {fails} failure")

    monkeypatch.setattr(dio.os, fails, broken)
    with pytest.raises(OSError, match="simulated"):
        dio.write_png(target, np.zeros((4, 4, 3)))
    monkeypatch.undo()
    assert os.listdir(tmp_path) == (["out.png"] if existing else [])
    if existing:
        assert target.read_bytes() == b"old"


def test_write_png_rejects_bad_images(tmp_path):
    with pytest.raises(ValueError, match=r"shape \(4, 4, 2\)"):
        dio.write_png(tmp_path / "a.png", np.zeros((4, 4, 2)))
    image = np.zeros((4, 4, 3))
    image[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match="1 values are NaN"):
        dio.write_png(tmp_path / "a.png", image)
    assert os.listdir(tmp_path) == []


def test_read_image_errors_name_the_path(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.png"):
        dio.read_image(tmp_path / "missing.png")
    (tmp_path / "junk.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="junk.png"):
        dio.read_image(tmp_path / "junk.png")
    np.save(tmp_path / "flat.npy", np.zeros(5))
    with pytest.raises(ValueError, match=r"flat.npy' holds float64 of shape \(5,\)"):
        dio.read_image(tmp_path / "flat.npy")
