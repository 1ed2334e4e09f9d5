"""The test order that keeps CI's two workers busy to the end (tests/conftest.py `deal`)."""

import itertools
from types import SimpleNamespace

import pytest
from conftest import deal, xdist_shares


def item(name, seconds=None):
    marker = SimpleNamespace(args=(seconds,)) if seconds is not None else None
    return SimpleNamespace(name=name, get_closest_marker=lambda _, m=marker: m)


@pytest.mark.parametrize("count,workers", [(10, 2), (11, 2), (7, 3), (3, 4)])
def test_shares_are_the_ones_worksteal_sends(count, workers):
    # worksteal: each idle node in turn gets len(pending) // nodes_remaining
    pending, sizes = count, []
    for left in range(workers, 0, -1):
        sizes.append(pending // left)
        pending -= sizes[-1]
    assert xdist_shares(count, workers) == sizes


def test_marked_tests_lead_each_share_and_balance_their_cost():
    light = [item(f"t{i}") for i in range(20)]
    heavy = [item("h170", 170), item("h100", 100), item("h90", 90), item("h75", 75)]
    items = light[:5] + heavy[:2] + light[5:15] + heavy[2:] + light[15:]
    ordered = deal(items, 2)
    assert sorted(i.name for i in ordered) == sorted(i.name for i in items)
    first, second = ordered[:12], ordered[12:]
    assert [i.name for i in first[:2]] == ["h170", "h75"]
    assert [i.name for i in second[:2]] == ["h100", "h90"]
    # the unmarked tests keep their collection order
    assert [i.name for i in ordered if i.name.startswith("t")] == [i.name for i in light]
    # every split of the marked tests between the shares is at least as uneven
    costs = [170, 100, 90, 75]
    best = min(abs(sum(c for c, s in zip(costs, side, strict=True) if s) * 2 - sum(costs))
               for side in itertools.product([0, 1], repeat=4))
    assert abs(245 - 190) == best


def test_a_module_marked_as_a_whole_is_dealt_as_one_unit():
    shared = SimpleNamespace(__name__="test_shared", pytestmark=[
        SimpleNamespace(name="cost", args=(80,))])
    together = [item(f"s{i}") for i in range(3)]
    for t in together:
        t.module = shared
        t.get_closest_marker = lambda _, m=shared.pytestmark[0]: m
    light = [item(f"t{i}") for i in range(9)]
    ordered = deal(light[:4] + [item("h100", 100)] + together + light[4:], 2)
    names = [i.name for i in ordered]
    assert names[:1] == ["h100"] and names[6:9] == ["s0", "s1", "s2"]
