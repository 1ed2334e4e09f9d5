"""Colour encodings: the sRGB transfer functions, and decoding by a file's declared transfer.

Colours are linear inside diffshade; image files hold encoded values. The sRGB curve is
the exact piecewise one of IEC 61966-2-1 (not the 2.2 power law):

    encode(x) = 12.92 x                      for x <= 0.0031308
              = 1.055 x^(1/2.4) - 0.055      otherwise
    decode(v) = v / 12.92                    for v <= 0.04045
              = ((v + 0.055) / 1.055)^2.4    otherwise

A *transfer* names how a file's values relate to linear light: "srgb", "linear", or a
float g, the PNG gAMA convention (encoded = linear^g, so linear = encoded^(1/g)).
Values are numpy arrays of any shape; outside [0, 1] the curves are extended as odd
functions, so that an over-range value round-trips.
"""

import numpy as np

__all__ = ["COLOR_SPACES", "decode", "encode", "linear_to_srgb", "srgb_to_linear"]

COLOR_SPACES = ("srgb", "linear")

_LINEAR_KNEE = 0.0031308  # linear value where the sRGB curve leaves its straight segment
_ENCODED_KNEE = 0.04045  # the same point on the encoded side
_SLOPE = 12.92
_A = 0.055
_GAMMA = 2.4


def srgb_to_linear(values):
    """sRGB-encoded values [...] -> linear values [...] (float64; IEC 61966-2-1)."""
    v = np.asarray(values, np.float64)
    a = np.abs(v)
    curve = ((np.maximum(a, _ENCODED_KNEE) + _A) / (1 + _A)) ** _GAMMA
    return np.sign(v) * np.where(a <= _ENCODED_KNEE, a / _SLOPE, curve)


def linear_to_srgb(values):
    """Linear values [...] -> sRGB-encoded values [...] (float64; IEC 61966-2-1)."""
    x = np.asarray(values, np.float64)
    a = np.abs(x)
    curve = (1 + _A) * np.maximum(a, _LINEAR_KNEE) ** (1 / _GAMMA) - _A
    return np.sign(x) * np.where(a <= _LINEAR_KNEE, a * _SLOPE, curve)


def _check(transfer):
    if transfer in COLOR_SPACES:
        return transfer
    if isinstance(transfer, (int, float)) and not isinstance(transfer, bool) and transfer > 0:
        return float(transfer)
    raise ValueError(f"transfer: got {transfer!r}; expected one of {COLOR_SPACES} or a "
                     "file gamma > 0")


def decode(values, transfer):
    """Encoded values [...] -> linear values [...] (float64) under `transfer`."""
    return _convert(values, transfer, srgb_to_linear, lambda gamma: 1.0 / gamma)


def encode(values, transfer):
    """Linear values [...] -> encoded values [...] (float64) under `transfer`."""
    return _convert(values, transfer, linear_to_srgb, lambda gamma: gamma)


def _convert(values, transfer, srgb, exponent):
    """values through the sRGB curve `srgb`, or a power law |v| ** exponent(gamma)."""
    transfer = _check(transfer)
    if transfer == "srgb":
        return srgb(values)
    v = np.asarray(values, np.float64)
    if transfer == "linear" or transfer == 1.0:
        return v
    return np.sign(v) * np.abs(v) ** exponent(transfer)
