"""The daemons' garbage-collection policy (hil.gcpolicy): no automatic full pass."""

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
    assert gc.get_freeze_count() == 0 and gc.get_threshold()[2] < 1000
