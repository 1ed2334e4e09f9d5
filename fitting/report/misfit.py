"""Does the model explain the images? The final residual against the noise and
quantization floor.

The right model leaves residuals r = rendered - target that are noise: independent from
pixel to pixel, and as large as the sensor noise and the 8-bit rounding of the targets.
A wrong mesh, camera, light or colour encoding leaves a residual that is smooth across
neighbouring pixels and larger than that floor. Over the kept pixels of every view:

    noise^2        = mean over pairs of horizontally or vertically adjacent kept pixels
                     of (r_i - r_j)^2 / 2   (white noise survives the difference; a smooth
                     misfit mostly cancels, so this over- rather than underestimates it)
    quantization^2 = mean of the variance of each target's rounding error when the
                     targets are 8-bit codes (step_i^2 / 12, step_i the width of the code's
                     interval in linear units: 1/255, or through the sRGB curve), or an
                     undistorted 8-bit photo (the bilinear mix of its pixels' variances
                     with squared weights); fitting.data.rounding. Else 0
    floor          = max(noise, quantization),   ratio = rms(r) / floor

The images are not explained when ratio > MAX_RATIO and rms(r) > MIN_RMS (half an 8-bit
level: a smaller residual is invisible in an 8-bit image, and float targets without noise
would otherwise have a floor of ~0).
"""

import dataclasses

import numpy as np

from fitting.report.uncertainty import kept_rounding, rows_fold
from fitting.solve.distribute import fit_data

MAX_RATIO = 3.0
MIN_RMS = 0.5 / 255.0
CAUSES = ("the mesh (shape, scale or placement), the cameras (pose or field of view), the "
          "lights (direction, position, colour or intensity), or the colour encoding of the "
          "targets (sRGB images read as linear or the reverse: dataset 'color_space' key, "
          "--color-space, docs/color.md)")


@dataclasses.dataclass(frozen=True)
class Misfit:
    """rms: of the residual; noise, quantization, floor: module docstring (linear units);
    ratio: rms / floor; explained: the model explains the images."""

    rms: float
    noise: float
    quantization: float
    floor: float
    ratio: float
    explained: bool

    def message(self, status="converged") -> str:
        """The warning when the images are not explained, else ''. status: the fit's
        (fitting.run); a fit that has not converged is named as the first suspect."""
        if self.explained:
            return ""
        head = (f"the model does not explain the images: the residual (RMS {self.rms:.3g}) "
                f"is {self.ratio:.3g} times the noise and quantization floor "
                f"({self.floor:.3g})")
        if status != "converged":
            return (f"{head}, and the fit has not converged (status {status!r}): take more "
                    "steps (--steps with --resume) or use the 'linear' method; if a "
                    f"converged fit still shows this, likely causes: {CAUSES}")
        return f"{head}; likely causes: {CAUSES}; see the residual images"

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def _neighbour_squares(r, pixels, width):
    """Sum of (r_i - r_j)^2 over right and lower neighbours that are both kept, and the
    number of such differences (pairs times channels)."""
    size = int(pixels.max(initial=0)) + width + 2
    row_of = np.full(size, -1)
    row_of[pixels] = np.arange(len(pixels))
    total, count = 0.0, 0
    for offset in (1, width):
        other = row_of[pixels + offset]
        keep = (other >= 0) & ((offset != 1) | ((pixels + 1) % width != 0))
        diff = r[keep] - r[other[keep]]
        total, count = total + float(np.sum(diff**2)), count + diff.size
    return total, count


def misfit(values, data, spec, widths, rounding=None) -> Misfit:
    """The Misfit of the physical `values` on the cached `data` (fitting.model.build_cache, or
    its ShardedViews: then a chunk of views at a time); widths: the image width of each
    view; rounding: each view's full-image Rounding (fitting.report.uncertainty.kept_rounding;
    None: from the targets' codes)."""
    base = fit_data(data)

    def add(total, rows, weight, view, target):
        for r, w, v in zip(rows[0], weight, view, strict=True):
            n = int(np.sum(w > 0))  # a view's kept pixels are its first rows
            if n:
                t, c = _neighbour_squares(r[:n], np.asarray(base.views[v].pixels), widths[v])
                total = (total[0] + float(np.sum(r[:n] ** 2)), total[1] + 3 * n,
                         total[2] + t, total[3] + c)
        return total

    squares, size, total, count = rows_fold(values, data, spec)(add, (0.0, 0, 0.0, 0))
    rms = float(np.sqrt(squares / size)) if size else 0.0
    noise = float(np.sqrt(total / (2 * count))) if count else 0.0
    kept = kept_rounding(data, rounding)
    quantization = 0.0 if kept is None else float(np.sqrt(
        sum(np.sum(r.variance) for r in kept) / max(sum(np.size(r.variance) for r in kept), 1)))
    floor = max(noise, quantization, 1e-12)
    ratio = rms / floor
    return Misfit(rms, noise, quantization, floor, ratio, not (ratio > MAX_RATIO and rms > MIN_RMS))
