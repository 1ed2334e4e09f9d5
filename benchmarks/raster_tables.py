"""Markdown tables of docs/soft-rasterization.md from benchmarks/raster.py's JSON.

    .venv/bin/python benchmarks/raster_tables.py [benchmarks/results/raster.json]
"""

import json
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _ms(seconds):
    return f"{seconds * 1e3:,.0f} ms"


def timing_table(results):
    rows = ["| faces | image | K | forward | fwd + bwd | compile fwd / fwd + bwd | dense fwd "
            "| dense fwd + bwd | speed-up fwd / fwd + bwd | dropped |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        if "error" in r:
            rows.append(f"| {r['config']} | failed | | | | | | | | |")
            continue
        fwd, fb, dense = r["forward"], r["forward_backward"], r.get("dense")
        dense_cells = ("| — | — | — " if dense is None else
                       f"| {dense['forward']['image_s']:,.1f} s "
                       f"| {dense['forward_backward']['image_s']:,.1f} s "
                       f"| {r['forward_speedup']:,.0f}× / {r['forward_backward_speedup']:,.0f}× ")
        rows.append(f"| {r['faces']:,} | {r['size']}² | {r['k']} | {_ms(fwd['median_s'])} "
                    f"| {_ms(fb['median_s'])} | {fwd['compile_s']:.1f} / {fb['compile_s']:.1f} s "
                    f"{dense_cells}| {r['dropped']:,} |")
    return "\n".join(rows)


def memory_table(results, faces):
    rows = ["| image | K | forward: B / px / K | fwd + bwd: B / px / K | fwd + bwd: XLA temp "
            "| fwd + bwd: peak RSS |", "|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        if "error" in r or r["faces"] != faces:
            continue
        fb = r["forward_backward"]
        rows.append(f"| {r['size']}² | {r['k']} | {r['forward']['bytes_per_pixel_per_k']:.0f} "
                    f"| {fb['bytes_per_pixel_per_k']:.0f} | {fb['temp_bytes'] / 1e9:.2f} GB "
                    f"| {r['peak_rss_bytes'] / 1e9:.2f} GB |")
    return "\n".join(rows)


def main():
    default = os.path.join(ROOT, "benchmarks/results/raster.json")
    path = sys.argv[1] if len(sys.argv) > 1 else default
    with open(path) as f:
        data = json.load(f)
    results = data["results"]
    print(f"<!-- {data['meta']['command']} -->\n")
    print(memory_table(results, max(r.get("faces", 0) for r in results)))
    print()
    print(timing_table(results))


if __name__ == "__main__":
    main()
