"""Shared parts of the bad-input catalogue (test_catalogue_render.py, test_catalogue_fit.py):
JSON mutations, folder snapshots and the one property every command must hold.

The property (docs/cli.md, "Exit status"): a command run in-process through
`diffshade.cli.main` either
- refuses its input: exit status 2, nothing on stdout, exactly one line on stderr that
  starts with `diffshade: error: `, names no temporary file and is not a library's own
  message (`UNCLEAR`), and every file under the watched folders byte for byte as it was
  (no output, no temporary, no folder made); or
- succeeds: exit status 0, and the caller's check of the output passes.
Any other exit status, or an exception out of `main` (which `diffshade` would print as a
traceback), fails the property.
"""

import copy
import json
import os
import shutil

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from diffshade import cli

# DIFFSHADE_CATALOGUE_EXAMPLES=500 explores further than CI's 40 examples (not derandomized
# then, so that each run draws new ones).
EXAMPLES = int(os.environ.get("DIFFSHADE_CATALOGUE_EXAMPLES", "0") or 0)
CATALOGUE_SETTINGS = settings(max_examples=EXAMPLES or 40, deadline=None,
                              derandomize=not EXAMPLES, database=None,
                              suppress_health_check=[HealthCheck.too_slow,
                                                     HealthCheck.function_scoped_fixture,
                                                     HealthCheck.filter_too_much])

# What a line must not hold: a hidden temporary's name, or the text of an exception raised
# inside numpy, Pillow or Python itself, which names neither the user's key nor what was
# expected (issue 26 lists each of these as seen).
UNCLEAR = (".tmp", "allow_pickle", "can not handle", "cannot identify image", "NoneType",
           "invalid literal", "object is not", "unhashable", "has no attribute",
           "list index", "string indices", "not subscriptable", "argument must be",
           "Traceback", "<_io.")

# A memory cap for the catalogue's commands (diffshade.budget): large enough for every
# valid 8x6 request (a point light's default 256-texel shadow cube needs ~0.3 GB), small
# enough that a huge size is refused by its cost instead of being tried on a shared
# machine.
MEMORY_LIMIT = "1G"

json_scalar = st.one_of(st.none(), st.booleans(), st.integers(-3, 10),
                        st.sampled_from([10**30, 2**31, 16385, -(10**30), 0.5, -0.0]),
                        st.floats(allow_nan=True, allow_infinity=True),
                        st.sampled_from(["", "x", "srgb", "linear", "phong", "point", "nan"]))
json_value = st.recursive(json_scalar, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.sampled_from(["a", "type", "width"]),
                                                 inner, max_size=2)), max_leaves=6)


def paths(value, prefix=()):
    """The key paths of every node of a JSON tree below its root."""
    items = value.items() if isinstance(value, dict) else \
        enumerate(value) if isinstance(value, list) else ()
    found = []
    for key, node in items:
        found += [(*prefix, key), *paths(node, (*prefix, key))]
    return found


def parent_of(value, path):
    """The node holding path[-1], or None where the path no longer exists."""
    for key in path[:-1]:
        if isinstance(value, dict) and key in value or \
                isinstance(value, list) and isinstance(key, int) and key < len(value):
            value = value[key]
        else:
            return None
    return value if isinstance(value, (dict, list)) else None


@st.composite
def mutated(draw, value, special=None, added=(), faults=3):
    """value (a JSON tree) with 1 (most often) to `faults` faults, each at a node drawn
    among its key paths and `added` (paths of keys the schema allows but value leaves out): the node
    replaced (by a value of `special[key]` for a key listed there, more often than not,
    else any JSON value), dropped, or a list item repeated. Where the faults go is drawn
    by a seeded Random: hypothesis's own draws start from the first choice (the first
    path, again and again), which would leave most of the tree untried in a few examples."""
    value, special = copy.deepcopy(value), special or {}
    rng = draw(st.randoms(use_true_random=False))
    for _ in range(rng.choice([1, 1, 1, *range(2, faults + 1)])):
        path = rng.choice(paths(value) + list(added))
        parent, key = parent_of(value, path), path[-1]
        if parent is None or isinstance(parent, list) != isinstance(key, int) or \
                isinstance(parent, list) and key >= len(parent):
            continue
        fault = rng.choice(["replace"] * 4 + ["drop", "copy"])
        if fault == "replace" or key not in parent and isinstance(parent, dict):
            strategy = special[key] if key in special and rng.random() < 0.75 else json_value
            # a copy: a later fault must not change a strategy's shared value
            parent[key] = copy.deepcopy(draw(strategy))
        elif fault == "drop":
            del parent[key]
        elif isinstance(parent, list):
            parent.append(copy.deepcopy(parent[key]))
    return value


@st.composite
def json_text(draw, value, special=None, added=()):
    """The JSON text of a mutated value, now and then cut short."""
    text = json.dumps(draw(mutated(value, special, added)))
    cut = draw(st.sampled_from([None] * 19 + [0.1, 0.5, 0.9]))
    return text if cut is None else text[: int(len(text) * cut)]


def snapshot(*folders):
    """{path: bytes, or None for a folder} of everything under the folders, hidden
    files included."""
    files = {}
    for folder in folders:
        for root, dirs, names in os.walk(folder):
            files.update({os.path.join(root, d): None for d in dirs})
            for name in names:
                with open(os.path.join(root, name), "rb") as file:
                    files[os.path.join(root, name)] = file.read()
    return files


def clear(path):
    """Remove a file or folder the last example wrote."""
    if os.path.isdir(path):
        shutil.rmtree(path)
    elif os.path.lexists(path):
        os.remove(path)


def refused_or_valid(capsys, argv, watched, check_output):
    """Run `diffshade ARGV` in-process; assert the module docstring's property, calling
    check_output(stdout) on success. Returns the exit status."""
    before = snapshot(*watched)
    code = cli.main(argv)
    out, err = capsys.readouterr()
    if code == 0:
        check_output(out)
        return code
    lines = err.splitlines()
    assert code == 2, f"exit status {code}: {err}"
    assert out == "" and len(lines) == 1, err
    line = lines[0]
    assert line.startswith("diffshade: error: ") and len(line) > 30, line
    assert not any(fragment in line for fragment in UNCLEAR), line
    after = snapshot(*watched)
    changed = sorted(p for p in set(after) | set(before)
                     if p not in after or p not in before or after[p] != before[p])
    assert not changed, f"{line}\nwritten or changed: {changed}"
    return code
