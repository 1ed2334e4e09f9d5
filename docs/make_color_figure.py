"""docs/img/color_decoding.png: one material fitted from 8-bit sRGB PNG targets, decoded
as linear (wrong) and as sRGB (right): target | fitted-wrong | fitted-right, each shown
sRGB-encoded as a screen expects, with the recovered numbers below.

    PYTHONPATH=. python docs/make_color_figure.py [--out docs/img/color_decoding.png]
"""

import argparse
import dataclasses
import os
import tempfile
import warnings

import numpy as np

import diffshade as ds
from data_synth import make_dataset
from fitting import fit, view_scene

TRUTH = ds.material(ka=(0.2, 0.15, 0.25), kd=(0.6, 0.45, 0.3), ks=(0.5, 0.45, 0.4),
                    shininess=60.0)
SIZE = 128


def png_dataset(dataset, folder, color_space):
    """Targets written as 8-bit sRGB PNGs and read back decoded as `color_space`."""
    views = []
    for i, view in enumerate(dataset.views):
        path = ds.write_png(os.path.join(folder, f"view_{i}.png"), view.target)
        views.append(dataclasses.replace(view, target=ds.read_image(path, color_space)))
    return dataclasses.replace(dataset, views=views)


def summary(material):
    def rgb(value):
        return "/".join(f"{v:.2f}" for v in np.broadcast_to(np.asarray(value), (3,)))
    return (f"ka {rgb(material.ka)}\nkd {rgb(material.kd)}\nks {rgb(material.ks)}\n"
            f"shininess {float(material.shininess):.1f}")


def main(argv=None):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "img",
                                                      "color_decoding.png"))
    args = parser.parse_args(argv)
    dataset = make_dataset("icosphere", TRUTH, n_views=3, n_lights=2, size=SIZE, seed=0)
    fitted, targets = {}, {}
    with tempfile.TemporaryDirectory() as folder, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name in ("linear", "srgb"):
            targets[name] = png_dataset(dataset, folder, name)
            fitted[name] = fit(targets[name]).material
    panels = [("target (8-bit sRGB PNG)", TRUTH, "true values"),
              ("fitted, PNG read as linear", fitted["linear"], "recovered (wrong)"),
              ("fitted, PNG decoded as sRGB", fitted["srgb"], "recovered (right)")]
    fig, axes = plt.subplots(1, 3, figsize=(9.6, 4.6))
    for ax, (title, material, label) in zip(axes, panels, strict=True):
        image = (targets["srgb"].views[0].target if material is TRUTH else
                 np.asarray(ds.render(view_scene(dataset, 0, material), dataset.settings)))
        ax.imshow(ds.linear_to_srgb(np.clip(image[..., :3], 0.0, 1.0)))
        ax.set_title(title, fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_xlabel(f"{label}\n{summary(material)}", fontsize=9, family="monospace")
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(args.out)
    for name, material in fitted.items():
        print(f"decoded as {name}:\n{summary(material)}")


if __name__ == "__main__":
    main()
