"""benchmarks/program_profile.py: the compiled program's thunks, each named by the HLO."""

import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))

from program_profile import hlo_table, profile  # noqa: E402

HLO = """\
  %negate_select_fusion = f32[256,256,8]{2,1,0} fusion(%a, %b), kind=kLoop, calls=%f.1, \
metadata={op_name="jit(loss)/transpose(jvp(jit(_render)))/jit(_where)/select_n" stack_frame_id=1}
  %diffshade_host_call.43 = (f32[5120,3]{1,0}, f32[5120,3]{1,0}) custom-call(%ids, %w), \
custom_call_target="diffshade_geometry_backward_f32", api_version=API_VERSION_TYPED_FFI
  ROOT %tuple.43 = (f32[], f32[3]{0}) tuple(%r, %g)
"""


def test_hlo_table_reads_shape_target_and_op_name_of_each_instruction():
    table = hlo_table(HLO)
    assert table["negate_select_fusion"] == (
        "f32[256,256,8]{2,1,0}", "", "jit(loss)/transpose(jvp(jit(_render)))/jit(_where)/select_n")
    assert table["diffshade_host_call.43"] == (
        "(f32[5120,3]{1,0}, f32[5120,3]{1,0})", "diffshade_geometry_backward_f32", "")
    assert table["tuple.43"] == ("(f32[], f32[3]{0})", "", "")


def test_profile_of_the_vertex_gradient_names_the_geometry_backward_kernel():
    calls = 2
    rows = profile(32, True, calls)
    kinds = {row[6] for row in rows}
    assert {"host", "forward", "reverse"} <= kinds
    targets = {row[4] for row in rows if row[6] == "host"}
    assert any(t.startswith("diffshade_geometry_backward") for t in targets), targets
    assert any(t.startswith("diffshade_search_soft") for t in targets), targets
    # slowest first, and each row's minimum is at most its median
    assert [row[1] for row in rows] == sorted((row[1] for row in rows), reverse=True)
    assert all(0.0 <= row[1] <= row[2] for row in rows)
    # the material's gradient runs no geometry backward
    material = {row[4] for row in profile(32, False, calls)}
    assert not any(t.startswith("diffshade_geometry_backward") for t in material)


def test_profile_of_the_forward_has_no_reverse_pass():
    rows = profile(32, None, 2)
    kinds = {row[6] for row in rows}
    assert "host" in kinds and "reverse" not in kinds
    targets = {row[4] for row in rows if row[6] == "host"}
    assert any(t.startswith("diffshade_geometry_forward") for t in targets), targets
    assert not any(t.startswith("diffshade_geometry_backward") for t in targets), targets
