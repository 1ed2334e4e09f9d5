"""What 8-bit rounding of the targets can do: each target value's worst-case rounding shift
and the variance of its rounding error, in linear units.

A target stored as 8-bit codes is off the value before rounding by at most half a code
step h (`steps_in`: 0.5 / 255 for linear codes; through the sRGB curve for sRGB codes, from
0.5 / 255 / 12.92 in the darks to ~0.0044 at 1), its error uniform on [-h, h] (variance
h^2 / 3). Codes are recognised in the target values themselves (`rounding_encoding`).

A photo undistorted on load (diffshade.io.undistort_image) is no longer codes: each pixel
is a bilinear mix sum w_k c_k of four photo codes. Its rounding is carried from the photo
instead (`resampled_rounding`): worst-case shift sum w_k h_k and, for independent errors,
variance sum w_k^2 h_k^2 / 3 (diffshade.io.undistort_rounding). A View keeps that
`Rounding` (fitting.data.views.View.rounding); `dataset_rounding` gives every view's,
from its View or from its codes. The fit's report uses them for the rounding bound, the
quantization floor of the misfit check and the held-out views' 8-bit PSNR limits.
"""

import dataclasses

import numpy as np

from diffshade.io import decode, encode, undistort_rounding


@dataclasses.dataclass(frozen=True)
class Rounding:
    """shift: [..., 3] worst-case |target - value before rounding| (linear); variance:
    [..., 3] the variance of that error (linear^2); srgb_variance: the same on sRGB values
    when known exactly (code targets), else None; source: how the targets were rounded,
    for the report's note (e.g. '8-bit (srgb-encoded)')."""

    shift: np.ndarray
    variance: np.ndarray
    srgb_variance: np.ndarray | None
    source: str

    def at(self, index) -> "Rounding":
        """The Rounding of the flat pixels `index` ([N] row * width + column): [N, 3]."""
        pick = lambda a: None if a is None else np.asarray(a).reshape(-1, 3)[index]
        return Rounding(pick(self.shift), pick(self.variance), pick(self.srgb_variance),
                        self.source)


def _codes_8bit(values, encoding):
    """values' 8-bit codes under `encoding`, or None when they are not all 8-bit codes."""
    codes = encode(values, encoding) * 255.0
    return np.round(codes) if np.all(np.abs(codes - np.round(codes)) < 1e-3) else None


def rounding_encoding(targets):
    """The encoding in which every array of `targets` (linear values, e.g. each view's)
    holds 8-bit codes: 'linear', else 'srgb', else None (rounding_steps)."""
    targets = list(targets)  # each converted in turn: one array's float64 copy at a time
    for encoding in ("linear", "srgb"):
        if all(_codes_8bit(np.asarray(t, np.float64), encoding) is not None
               for t in targets):
            return encoding
    return None


def steps_in(targets, encoding):
    """rounding_steps of 8-bit `targets` (float64) in a known encoding (rounding_encoding)."""
    if encoding == "linear":
        return np.full(targets.shape, 0.5 / 255.0)
    codes = np.round(encode(targets, encoding) * 255.0)
    centre = decode(codes / 255.0, "srgb")
    above = decode(np.minimum(codes + 0.5, 255.0) / 255.0, "srgb") - centre
    below = centre - decode(np.maximum(codes - 0.5, 0.0) / 255.0, "srgb")
    return np.maximum(above, below)


def rounding_steps(targets):
    """Worst-case |linear target - the value before 8-bit rounding| per value of `targets`
    (linear, [...]), or (None, None) when they are not 8-bit codes; with the encoding the
    codes were found in: 'linear' (0.5 / 255 everywhere) or 'srgb' (half a code step,
    mapped through the sRGB curve)."""
    targets = np.asarray(targets, np.float64)
    encoding = rounding_encoding([targets])
    return (None, None) if encoding is None else (steps_in(targets, encoding), encoding)


def code_rounding(target, encoding) -> Rounding:
    """The Rounding of `target` (linear values of 8-bit codes in `encoding`)."""
    target = np.asarray(target, np.float64)
    half = steps_in(target, encoding)
    if encoding == "srgb":
        srgb_half = np.full(target.shape, 0.5 / 255.0)
    else:  # a linear code's interval, seen through the sRGB curve
        step = 0.5 / 255.0
        srgb_half = (encode(np.minimum(target + step, 1.0), "srgb")
                     - encode(np.maximum(target - step, 0.0), "srgb")) / 2.0
    return Rounding(half, half**2 / 3.0, srgb_half**2 / 3.0, f"8-bit ({encoding}-encoded)")


def resampled_rounding(photo, camera) -> Rounding | None:
    """The Rounding of the pinhole image undistort_image(photo, camera) makes of an 8-bit
    photo (linear values, [H, W, 3]), or None when the photo is not 8-bit codes."""
    half, encoding = rounding_steps(photo)
    if half is None:
        return None
    shift, variance = undistort_rounding(half, camera)
    return Rounding(shift, variance, None, f"8-bit ({encoding}-encoded), resampled on load "
                    "(undistorted)")


def dataset_rounding(views):
    """Per view of `views` (Views, or anything with a `target`), its Rounding: the View's
    own `rounding` when it has one, else its code_rounding in the encoding every such
    target shares (rounding_encoding); None when some target has neither."""
    views = list(views)
    plain = [v.target for v in views if getattr(v, "rounding", None) is None]
    encoding = rounding_encoding(plain) if plain else "linear"
    if encoding is None:
        return None
    return tuple(v.rounding if getattr(v, "rounding", None) is not None
                 else code_rounding(v.target, encoding) for v in views)


def carried_rounding(views):
    """dataset_rounding(views) when some View carries its own rounding (an undistorted
    photo), else None: code targets are read where they are used (their kept pixels)."""
    views = list(views)
    return dataset_rounding(views) if any(v.rounding is not None for v in views) else None
