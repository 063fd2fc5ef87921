"""The daemons' garbage-collection policy (hil.gcpolicy): no automatic pass."""

import gc
import weakref

from hil.gcpolicy import GcPolicy


class _Node:
    def __init__(self) -> None:
        self.other = self  # a reference cycle: only the collector frees it


def test_full_passes_are_the_daemons_and_startup_objects_are_frozen() -> None:
    policy = GcPolicy(full_every_s=0.0)
    try:
        assert gc.get_freeze_count() > 0
        node = _Node()
        alive = weakref.ref(node)
        kept = [_Node() for _ in range(20_000)]  # long-lived: promoted with the node
        for _ in range(2):
            gc.collect(1)
        del node, kept  # 20,001 objects of cyclic garbage in the oldest generation
        for _ in range(50):  # allocations that live a while: the interpreter's young passes
            young = [[] for _ in range(2_000)]
            del young
        assert alive() is not None  # no automatic full pass (without the policy: one)
        policy.after_tick()
        assert alive() is None and policy.counters()["gc_full"] == 1
    finally:
        policy.restore()
    assert gc.get_freeze_count() == 0 and gc.isenabled()


def test_no_pass_starts_inside_a_tick_and_young_cycles_go_after_it() -> None:
    """Automatic collection is off, so a tick's allocations never start a pass (a
    generation-1 pass cost 2 ms of a 25 ms tick); after_tick collects the young
    generations (its time counted), so a cycle made during a tick is freed after it."""
    passes = []

    def seen(phase, info) -> None:
        if phase == "start":
            passes.append(info["generation"])

    policy = GcPolicy(full_every_s=3600.0)
    gc.callbacks.append(seen)
    try:
        node = _Node()
        alive = weakref.ref(node)
        del node
        for _ in range(50):  # a tick's worth of allocations, and more
            young = [[] for _ in range(2_000)]
            del young
        assert passes == [] and alive() is not None
        for _ in range(policy.young_every):
            policy.after_tick()
        assert alive() is None
        assert passes == [0] * (policy.young_every - 1) + [1]
        c = policy.counters()
        assert c["gc_young"] == policy.young_every and c["gc_full"] == 0
        assert 0 < c["gc_young_ms_mean"] <= c["gc_young_ms_max"]
        policy._last_pass -= 2.0  # a second without ticks: idle() collects
        policy.idle()
        assert policy.counters()["gc_young"] == policy.young_every + 1
        policy.idle()  # just collected: nothing
        assert policy.counters()["gc_young"] == policy.young_every + 1
    finally:
        gc.callbacks.remove(seen)
        policy.restore()
    assert gc.isenabled()
