"""Warnings scored by vehicle (issue 27): a warning on the wrong vehicle is a false
positive on it and a false negative on the right one, never a true positive."""

from catc.apps.verdict import Confusion, accuracy, by_app, tick_confusion


def test_one_tick_by_hand():
    assert tick_confusion({"LEAD"}, {"LEAD"}) == (1, 0, 0, 0)
    assert tick_confusion({"LEAD"}, {"GHOST"}) == (0, 0, 1, 1)  # the wrong vehicle
    assert tick_confusion({"LEAD"}, {"LEAD", "GHOST"}) == (1, 0, 1, 0)
    assert tick_confusion({"LEAD"}, set()) == (0, 0, 0, 1)
    assert tick_confusion(set(), {"GHOST"}) == (0, 0, 1, 0)
    assert tick_confusion(set(), set()) == (0, 1, 0, 0)


def test_a_run_of_ticks_per_app():
    c = Confusion(("fcw", "bsw"))
    lead, ghost = 0x1234, 0x6A7A0000
    c.add({"fcw": [lead]}, by_app([("fcw", lead)]))  # right
    c.add({"fcw": [lead]}, by_app([("fcw", ghost)]))  # wrong vehicle
    c.add({}, {})  # quiet
    c.add({"bsw": [ghost]}, by_app([("bsw", ghost), ("fcw", ghost)]))
    d = c.as_dict()
    assert {k: d["fcw"][k] for k in ("tp", "tn", "fp", "fn")} == \
        {"tp": 1, "tn": 1, "fp": 2, "fn": 1}
    assert d["fcw"]["accuracy"] == round(2 / 5, 4)
    assert {k: d["bsw"][k] for k in ("tp", "tn", "fp", "fn")} == \
        {"tp": 1, "tn": 3, "fp": 0, "fn": 0}
    assert accuracy(dict.fromkeys(("tp", "tn", "fp", "fn"), 0)) is None
