"""Colour encoding: the sRGB transfer functions (diffshade.io.color), image files decoded to
linear on read and encoded on write (diffshade.io.images, diffshade.io.png), the dataset's
"color_space" key and `diffshade fit --color-space`, and the 8-bit sRGB rounding bound.

References: the IEC 61966-2-1 closed form evaluated with Python's math per element,
published values, PNG bytes decoded by pillow, rows filtered by a plain-Python PNG
filter written here, and fits against the known true material. The end-to-end test fits
8-bit sRGB PNGs of a trimesh capsule with `diffshade fit`, and shows that the same files
read as linear give a clearly worse fit."""

import dataclasses
import json
import os
import struct
import zlib

import imageio.v3 as iio
import numpy as np
import pytest
import trimesh

import diffshade as ds
import diffshade.io.images as dio
from data_synth import load_dataset, make_dataset, save_dataset
from diffshade import cli
from diffshade.io.color import decode, encode, linear_to_srgb, srgb_to_linear
from diffshade.io.png import SIGNATURE, decode_png16, encode_png
from fitting import fit
from fitting.data.rounding import rounding_steps

# ---- the transfer functions ----


def closed_form_decode(v):
    return v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4


def closed_form_encode(x):
    return 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1 / 2.4) - 0.055


def test_transfer_functions_match_the_closed_form_at_every_8bit_code():
    codes = np.arange(256) / 255.0
    want = [closed_form_decode(v) for v in codes]
    np.testing.assert_allclose(srgb_to_linear(codes), want, rtol=1e-14, atol=0)
    xs = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(linear_to_srgb(xs), [closed_form_encode(x) for x in xs],
                               rtol=1e-14, atol=0)


@pytest.mark.parametrize("linear, encoded", [
    (0.0, 0.0), (1.0, 1.0), (0.0031308, 0.040449936), (0.001, 0.01292),
    (0.18, 0.46135612950044164),  # 18 % grey
    (0.21404114048223255, 0.5), (0.5, 0.7353569830524495)])
def test_transfer_functions_at_known_points(linear, encoded):
    assert linear_to_srgb(linear) == pytest.approx(encoded, rel=1e-9, abs=1e-12)
    assert srgb_to_linear(encoded) == pytest.approx(linear, rel=1e-9, abs=1e-12)


def test_transfer_functions_round_trip_and_are_continuous_at_the_knee():
    xs = np.concatenate([np.linspace(-0.5, 1.5, 20001), np.geomspace(1e-9, 1.0, 500)])
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(xs)), xs, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(xs)), xs, rtol=1e-12, atol=1e-15)
    # the two branches meet at the knee (to the standard's 5 digits) and the curve rises
    assert 12.92 * 0.0031308 == pytest.approx(1.055 * 0.0031308 ** (1 / 2.4) - 0.055, abs=1e-7)
    assert np.all(np.diff(linear_to_srgb(np.linspace(0, 1, 10001))) > 0)


def test_a_file_gamma_is_a_power_law():
    v = np.linspace(0.0, 1.0, 11)
    np.testing.assert_allclose(decode(v, 0.5), v ** 2.0)
    np.testing.assert_allclose(encode(decode(v, 0.45), 0.45), v, atol=1e-15)
    np.testing.assert_array_equal(decode(v, "linear"), v)
    with pytest.raises(ValueError, match="transfer: got 'rec709'"):
        decode(v, "rec709")


# ---- files ----


@pytest.mark.parametrize("color_space", ["srgb", "linear"])
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_8bit_png_round_trip(tmp_path, color_space, channels):
    image = np.resize(np.linspace(-0.1, 1.1, 37), (4, 9, channels))
    path = dio.write_png(tmp_path / "a.png", image, color_space=color_space)
    stored = iio.imread(path, plugin="pillow").reshape(4, 9, channels)
    colour = slice(0, 3) if channels == 4 else slice(None)
    want = np.clip(image, 0, 1)
    want[..., colour] = encode(want[..., colour], color_space)
    np.testing.assert_array_equal(stored, np.round(want * 255))
    assert dio.image_transfer(path) == color_space
    got = dio.read_image(path)
    expected = stored / 255.0
    expected[..., colour] = decode(expected[..., colour], color_space)
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-9)
    # a second write of what was read stores the same codes
    again = dio.write_png(tmp_path / "b.png", got, color_space=color_space)
    np.testing.assert_array_equal(iio.imread(again, plugin="pillow").reshape(stored.shape),
                                  stored)


def test_16bit_png_gradient_round_trips_below_one_level(tmp_path):
    codes = np.arange(65536, dtype=np.float64).reshape(256, 256) / 65535.0
    encoded = np.stack([codes, codes[::-1], codes.T], axis=-1)
    linear = srgb_to_linear(encoded)
    path = dio.write_png(tmp_path / "g.png", linear, bits=16)
    got = dio.read_image(path)
    assert got.dtype == np.float32 and got.shape == (256, 256, 3)
    assert np.abs(linear_to_srgb(got) - encoded).max() * 65535 < 0.01
    assert np.abs(got - linear).max() * 65535 < 0.01
    # pillow reads 16-bit grey exactly: the file holds round(encoded * 65535)
    grey = dio.write_png(tmp_path / "grey.png", linear[..., :1], bits=16)
    np.testing.assert_array_equal(iio.imread(grey, plugin="pillow"), np.round(codes * 65535))


def paeth(a, b, c):
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    return a if pa <= pb and pa <= pc else b if pb <= pc else c


def filtered_png16(codes, filters):
    """A 16-bit RGB PNG whose rows use the given filter types (plain Python)."""
    height, width, _ = codes.shape
    rows = [bytes(np.ascontiguousarray(r, ">u2").tobytes()) for r in codes]
    bpp, out, prev = 6, b"", bytes(len(rows[0]))
    for row, kind in zip(rows, filters, strict=True):
        line = bytearray([kind])
        for i, x in enumerate(row):
            a = row[i - bpp] if i >= bpp else 0
            b, c = prev[i], prev[i - bpp] if i >= bpp else 0
            pred = [0, a, b, (a + b) // 2, paeth(a, b, c)][kind]
            line.append((x - pred) % 256)
        out, prev = out + bytes(line), row

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(
            ">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    header = struct.pack(">IIBBBBB", width, height, 16, 2, 0, 0, 0)
    return SIGNATURE + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(out)) + chunk(
        b"IEND", b"")


def test_16bit_png_decoder_undoes_every_row_filter():
    codes = np.random.default_rng(0).integers(0, 65536, (10, 7, 3)).astype(np.uint16)
    data = filtered_png16(codes, [0, 1, 2, 3, 4, 4, 3, 2, 1, 0])
    np.testing.assert_array_equal(decode_png16(data), codes)


def png_with(tmp_path, name, chunks, value=128):
    path = tmp_path / name
    path.write_bytes(encode_png(np.full((2, 3, 3), value, np.uint8), chunks))
    return path


GAMA = lambda g: (b"gAMA", struct.pack(">I", g))  # noqa: E731


@pytest.mark.parametrize("chunks, transfer", [
    ([], "srgb"),  # untagged integer images are sRGB
    ([GAMA(100000)], "linear"),
    ([GAMA(45455)], "srgb"),
    ([GAMA(50000)], 0.5),
    ([(b"sRGB", b"\x00"), GAMA(100000)], "srgb"),  # sRGB wins over gAMA
    ([(b"cICP", bytes([1, 8, 0, 1])), (b"sRGB", b"\x00")], "linear"),  # cICP wins
    ([(b"cICP", bytes([1, 13, 0, 1])), GAMA(100000)], "srgb")])
def test_png_colour_chunks_are_honoured(tmp_path, chunks, transfer):
    path = png_with(tmp_path, "c.png", chunks)
    assert dio.image_transfer(path) == transfer
    np.testing.assert_allclose(dio.read_image(path), decode(np.full((2, 3, 3), 128 / 255),
                                                            transfer), rtol=1e-6)
    # an explicit colour space overrides what the file says
    np.testing.assert_allclose(dio.read_image(path, "linear"), 128 / 255, rtol=1e-6)


def test_jpeg_is_decoded_as_srgb(tmp_path):
    path = tmp_path / "flat.jpg"
    iio.imwrite(path, np.full((16, 16, 3), (200, 100, 30), np.uint8), plugin="pillow",
                quality=100)
    raw = iio.imread(path, plugin="pillow") / 255.0
    assert dio.image_transfer(path) == "srgb"
    np.testing.assert_allclose(dio.read_image(path), srgb_to_linear(raw), rtol=1e-6)
    assert np.abs(dio.read_image(path)[4, 4] - srgb_to_linear(np.array([200, 100, 30]) / 255)
                  ).max() < 0.01


def test_npy_is_linear_whatever_the_colour_space(tmp_path):
    image = np.random.default_rng(1).uniform(-0.1, 1.2, (3, 4, 3)).astype(np.float32)
    path = dio.write_npy(tmp_path / "a.npy", image)
    assert dio.image_transfer(path) == "linear"
    for color_space in (None, "srgb", "linear"):
        np.testing.assert_array_equal(dio.read_image(path, color_space), image)
    with pytest.raises(ValueError, match="color_space: got 'rgb'"):
        dio.read_image(path, "rgb")
    with pytest.raises(ValueError, match="bits: got 12"):
        dio.write_png(tmp_path / "a.png", image, bits=12)


# ---- datasets ----

TRUTH = ds.material(ka=(0.2, 0.15, 0.25), kd=(0.6, 0.45, 0.3), ks=(0.5, 0.45, 0.4),
                    shininess=60.0)


def png_only(dataset, folder, key=None, view_keys=None):
    """save_dataset without the .npy targets (the fit reads the PNGs), with optional
    dataset-level and per-view "color_space" keys."""
    save_dataset(dataset, folder)
    meta = json.loads((folder / "dataset.json").read_text())
    for i, entry in enumerate(meta["views"]):
        os.remove(folder / entry.pop("target"))
        if view_keys and view_keys[i]:
            entry["color_space"] = view_keys[i]
    if key:
        meta["color_space"] = key
    (folder / "dataset.json").write_text(json.dumps(meta))
    return folder


@pytest.fixture(scope="module")
def sphere():
    return make_dataset(ds.icosphere(2), TRUTH, n_views=1, n_lights=2, size=24, seed=2)


def test_dataset_key_and_argument_decide_the_decoding(sphere, tmp_path):
    target = sphere.views[0].target
    codes = np.round(linear_to_srgb(np.clip(target, 0, 1)) * 255) / 255
    as_srgb, as_linear = srgb_to_linear(codes), codes
    cases = [(None, None, None, as_srgb), ("linear", None, None, as_linear),
             ("linear", ["srgb", None], None, as_srgb),  # the view's key wins
             ("linear", ["srgb", None], "linear", as_linear),  # the argument wins
             (None, None, "linear", as_linear),
             ("LINEAR", ["sRGB", None], None, as_srgb)]  # names in any case
    for i, (key, view_keys, argument, want) in enumerate(cases):
        folder = png_only(sphere, tmp_path / f"d{i}", key, view_keys)
        got = load_dataset(folder, argument).views[0].target
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9, err_msg=str(i))
    folder = png_only(sphere, tmp_path / "bad", "adobe-rgb")
    with pytest.raises(ValueError, match="dataset.json: color_space: got 'adobe-rgb'; "
                       "expected"):
        load_dataset(folder)


def test_npy_targets_win_over_the_key(sphere, tmp_path):
    save_dataset(sphere, tmp_path / "d")
    meta = json.loads((tmp_path / "d" / "dataset.json").read_text())
    (tmp_path / "d" / "dataset.json").write_text(json.dumps(meta | {"color_space": "linear"}))
    np.testing.assert_array_equal(load_dataset(tmp_path / "d").views[0].target,
                                  sphere.views[0].target)


def srgb_8bit(dataset):
    """The dataset with its targets rounded as an 8-bit sRGB PNG stores them."""
    views = [dataclasses.replace(v, target=srgb_to_linear(np.round(linear_to_srgb(
        np.clip(v.target, 0, 1)) * 255) / 255)) for v in dataset.views]
    return dataclasses.replace(dataset, views=views)


def test_rounding_bound_of_srgb_8bit_targets_covers_the_error(sphere):
    steps, encoding = rounding_steps(srgb_to_linear(np.arange(256) / 255))
    assert encoding == "srgb"
    assert steps[0] == pytest.approx(0.5 / 255 / 12.92) and steps[-1] == pytest.approx(
        1 - srgb_to_linear(254.5 / 255))
    result = fit(srgb_8bit(sphere))
    report = result.uncertainty
    truth = np.concatenate([np.ravel(np.asarray(getattr(TRUTH, k), np.float64))
                            for k in ("ka", "kd", "ks", "shininess")])
    assert report.rounding_bound is not None and "srgb-encoded" in report.notes[0]
    assert np.all(np.abs(report.values - truth) <= report.rounding_bound)


# ---- end to end: 8-bit sRGB PNGs of a trimesh capsule, fitted by `diffshade fit` ----


def fit_cli(folder, out, capsys, *extra):
    code = cli.main(["fit", str(folder), "-o", str(out), "--quiet", *extra])
    capsys.readouterr()
    assert code == 0
    result = json.loads((out / "result.json").read_text())
    return {k: np.abs(np.asarray(result["material"][k]) / np.asarray(result["truth"][k]) - 1)
            for k in ("kd", "ks", "shininess")}, result


def test_srgb_pngs_of_a_capsule_fit_only_when_decoded_as_srgb(tmp_path, capsys):
    capsule = ds.mesh_from_trimesh(trimesh.creation.capsule(height=1.0, radius=0.5, count=[24,
                                                                                           24]))
    dataset = make_dataset(capsule, TRUTH, n_views=2, n_lights=2, size=64, seed=0)
    folder = png_only(dataset, tmp_path / "capsule")
    assert dio.image_transfer(folder / "view_000.png") == "srgb"

    right, result = fit_cli(folder, tmp_path / "right", capsys)
    assert max(e.max() for e in right.values()) < 0.03, right
    assert result["color_space"] is None
    assert dio.image_transfer(tmp_path / "right" / "view_000.png") == "srgb"  # the panels

    meta = json.loads((folder / "dataset.json").read_text())
    (folder / "dataset.json").write_text(json.dumps(meta | {"color_space": "linear"}))
    wrong, _ = fit_cli(folder, tmp_path / "wrong", capsys)
    assert wrong["kd"].max() > 0.2 and wrong["ks"].max() > 0.2, wrong  # >= 7x the right error

    flag, result = fit_cli(folder, tmp_path / "flag", capsys, "--color-space", "srgb")
    assert result["color_space"] == "srgb"
    for name in right:
        np.testing.assert_allclose(flag[name], right[name], atol=1e-6)
