"""A compiled JAX program (jax.stages.Compiled) as plain data and back, without pickle.

    header, code = describe(compiled, device)   # a JSON-ready dict, XLA's executable bytes
    compiled = rebuild(header, code, in_tree, device)

jax.experimental.serialize_executable pickles the Python wrapper of an executable, and
unpickling a file can run any code. Here the wrapper's pieces are data: the shapes and
dtypes of the arguments and results, which arguments the program kept, the tree structure
of its result and its name. A result's node types are named by module and qualified name
and found again only among the builtin containers and the classes of diffshade and
fitting modules already imported (nothing is imported, nothing else is looked up); their
auxiliary data must be plain JSON. The machine code goes through XLA's deserializer only
(Client.deserialize_executable), as in JAX's own persistent cache.

A program whose wrapper holds anything else (effects, host callbacks, mutable arrays,
constants, donated or sharded arguments, a node type from elsewhere, auxiliary data that is
not plain JSON) cannot be described: describe raises Unstorable and the caller keeps no
copy. rebuild raises ValueError for a header that does not describe a program.

It reads JAX's internals (jax._src.interpreters.pxla), as serialize_executable does: a
header is only read by the JAX version that wrote it (the program store's key holds it).
"""

import sys

import jax
import numpy as np
from jax._src import core
from jax._src.interpreters import pxla
from jax._src.lib import xla_client
from jax.sharding import SingleDeviceSharding

__all__ = ["Unstorable", "describe", "rebuild"]

BUILTIN_NODES = {"tuple": tuple, "list": list, "dict": dict, "None": type(None)}
PROJECT_MODULES = ("diffshade", "fitting")


class Unstorable(Exception):
    """A compiled program whose wrapper is not plain data (the message says what)."""


# ---- arrays' abstract values ----


def _aval_data(aval):
    if type(aval) is not core.ShapedArray:
        raise Unstorable(f"an argument or result of type {type(aval).__name__}")
    data = [list(aval.shape), str(aval.dtype), bool(aval.weak_type)]
    if _aval(data) != aval:  # a sharding, memory space ... that the data does not hold
        raise Unstorable(f"an abstract value not rebuilt from its shape and dtype: {aval}")
    return data


def _aval(data):
    shape, dtype, weak = data
    if not (isinstance(shape, list) and all(type(n) is int and n >= 0 for n in shape)
            and isinstance(dtype, str) and isinstance(weak, bool)):
        raise ValueError(f"not an abstract value: {data!r}")
    return core.ShapedArray(tuple(shape), np.dtype(dtype), weak_type=weak)


# ---- tree structures ----


def _type_name(cls):
    for name, builtin in BUILTIN_NODES.items():
        if cls is builtin:
            return name
    if cls.__module__.split(".")[0] not in PROJECT_MODULES:
        raise Unstorable(f"a result node of type {cls.__module__}.{cls.__qualname__}")
    return f"{cls.__module__}:{cls.__qualname__}"


def _node_type(name):
    """The class a node type name stands for: a builtin container, or a class of an
    already imported diffshade or fitting module (never an import)."""
    if not isinstance(name, str):
        raise ValueError(f"not a node type: {name!r}")
    if name in BUILTIN_NODES:
        return BUILTIN_NODES[name]
    module, _, qualname = name.partition(":")
    found = sys.modules.get(module) if module.split(".")[0] in PROJECT_MODULES else None
    for part in qualname.split("."):
        found = getattr(found, part, None)
    if not isinstance(found, type):
        raise ValueError(f"not a node type of diffshade or fitting: {name!r}")
    return found


def _aux_data(value):
    """Auxiliary data as JSON: tuples tagged, so that they come back as tuples."""
    if value is None or type(value) in (bool, int, str):
        return value
    if type(value) is float and np.isfinite(value):
        return value
    if type(value) in (tuple, list):
        items = [_aux_data(v) for v in value]
        return {"tuple": items} if type(value) is tuple else {"list": items}
    raise Unstorable(f"auxiliary data of type {type(value).__name__} in a result's structure")


def _aux(data):
    if data is None or type(data) in (bool, int, float, str):
        return data
    if isinstance(data, dict) and len(data) == 1 and set(data) <= {"tuple", "list"}:
        (tag, items), = data.items()
        if isinstance(items, list):
            values = [_aux(v) for v in items]
            return tuple(values) if tag == "tuple" else values
    raise ValueError(f"not auxiliary data: {data!r}")


def tree_data(treedef):
    """A tree structure as JSON: '*' for a leaf, else [type, aux data, [children]]."""
    node = treedef.node_data()
    if node is None:
        return "*"
    cls, aux = node
    return [_type_name(cls), _aux_data(aux), [tree_data(c) for c in treedef.children()]]


def tree_from_data(data):
    """The tree structure that tree_data described (ValueError when it is not one)."""
    if data == "*":
        return jax.tree.structure(0)
    if not (isinstance(data, list) and len(data) == 3 and isinstance(data[2], list)):
        raise ValueError(f"not a tree structure: {data!r}")
    name, aux, children = data
    try:
        return jax.tree_util.PyTreeDef.from_node_data_and_children(
            jax.tree_util.default_registry, (_node_type(name), _aux(aux)),
            [tree_from_data(c) for c in children])
    except (TypeError, RuntimeError) as err:
        raise ValueError(f"not a tree structure: {err}") from None


# ---- programs ----


def _unloaded(compiled):
    """The program's wrapper, checked to hold nothing but what the header describes."""
    unloaded = getattr(compiled._executable, "_unloaded_executable", None)
    if unloaded is None:
        raise Unstorable("a program JAX cannot serialize")
    if compiled._params.const_args:
        raise Unstorable("a program with constant arguments")
    for name in ("unordered_effects", "ordered_effects", "keepalive", "host_callbacks"):
        if getattr(unloaded, name):
            raise Unstorable(f"a program with {name.replace('_', ' ')}")
    if unloaded.mut is not None or unloaded.pgle_profiler is not None:
        raise Unstorable("a program with mutable arrays or a profiler")
    return unloaded


def _memory_kinds(shardings, device):
    kinds = []
    for sharding in shardings:
        if not (isinstance(sharding, SingleDeviceSharding)
                and sharding.device_set == {device}):
            raise Unstorable(f"a program sharded as {sharding}")
        kinds.append(sharding.memory_kind)
    return kinds


def describe(compiled, device):
    """(header, code) of a Compiled program that runs on `device`: a JSON-ready dict and
    XLA's serialized executable. Raises Unstorable (above)."""
    unloaded = _unloaded(compiled)
    args = jax.tree.leaves(compiled.args_info)
    if any(arg.donated for arg in args):
        raise Unstorable("a program with donated arguments")
    header = {
        "name": unloaded.name, "committed": bool(unloaded.committed),
        "no_kwargs": bool(compiled._no_kwargs),
        "arguments": [_aval_data(arg._aval) for arg in args],
        "kept": sorted(unloaded.kept_var_idx),
        "results": [_aval_data(aval) for aval in unloaded.output_avals],
        "input_memory": _memory_kinds(unloaded.input_shardings, device),
        "output_memory": _memory_kinds(unloaded.output_shardings, device),
        "out_tree": tree_data(compiled.out_tree),
    }
    if [_aval(header["arguments"][i]) for i in header["kept"]] != list(unloaded.input_avals):
        raise Unstorable("a program whose kept arguments are not its inputs")
    if tree_from_data(header["out_tree"]) != compiled.out_tree:
        raise Unstorable(f"a result structure not rebuilt from its data: {compiled.out_tree}")
    return header, unloaded.xla_executable.serialize()


def _checked(header, in_tree):
    """(arguments, kept, results, out_tree) of a header; ValueError when inconsistent."""
    arguments = [_aval(a) for a in header["arguments"]]
    kept, results = header["kept"], [_aval(r) for r in header["results"]]
    out_tree = tree_from_data(header["out_tree"])
    if len(arguments) != in_tree.num_leaves or out_tree.num_leaves != len(results):
        raise ValueError("the header's arguments or results do not match its structures")
    if not (isinstance(kept, list) and kept == sorted(set(kept))
            and all(type(i) is int and 0 <= i < len(arguments) for i in kept)):
        raise ValueError(f"kept arguments: {kept!r}")
    if len(header["input_memory"]) != len(kept) or len(header["output_memory"]) != len(results):
        raise ValueError("the header's memory kinds do not match its arguments or results")
    return arguments, kept, results, out_tree


def rebuild(header, code, in_tree, device):
    """The Compiled program that describe(...) gave `header` and `code` for, loaded on
    `device`; in_tree: the structure of its (positional, keyword) arguments."""
    try:
        arguments, kept, results, out_tree = _checked(header, in_tree)
        inputs = [arguments[i] for i in kept]
        in_shardings = [SingleDeviceSharding(device, memory_kind=k)
                        for k in header["input_memory"]]
        out_shardings = [SingleDeviceSharding(device, memory_kind=k)
                         for k in header["output_memory"]]
        name, committed = str(header["name"]), bool(header["committed"])
        no_kwargs = bool(header["no_kwargs"])
    except (KeyError, TypeError) as err:
        raise ValueError(f"not a program header: {err!r}") from None
    devices = xla_client.DeviceList((device,))
    executable = device.client.deserialize_executable(code, executable_devices=devices)
    in_layouts, out_layouts = pxla._get_layouts_from_executable(
        executable, [None] * len(inputs), [None] * len(results), 0, inputs, results)
    unloaded = pxla.UnloadedMeshExecutable(
        xla_executable=executable, device_list=devices, backend=device.client,
        input_avals=inputs, input_shardings=in_shardings, output_avals=results,
        output_shardings=out_shardings, committed=committed, name=name,
        unordered_effects=[], ordered_effects=[], keepalive=[], host_callbacks=[],
        kept_var_idx=set(kept), mut=None, xla_in_layouts=in_layouts,
        dispatch_in_layouts=pxla.get_dispatch_layouts(in_layouts, in_shardings, inputs),
        xla_out_layouts=out_layouts,
        all_args_info=pxla.AllArgsInfo(arguments, core.DebugInfo("jit", name, None, None)),
        pgle_profiler=None)
    args_info = in_tree.unflatten([jax.stages.ArgInfo(a, False) for a in arguments])
    return jax.stages.Compiled(unloaded.load(), [], args_info, out_tree, no_kwargs=no_kwargs)
