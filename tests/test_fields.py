"""`jaxrender.io.Fields`: typed reads of a document that collect every problem with its location,
and `Problems`, which stops at its limit (a huge bad input fails fast)."""

import numpy as np
import pytest

from jaxrender.io import Fields, InputErrors, Problems

DOC = {"a": {"n": 3, "x": [1, 2, 3], "c": "srgb", "rgb": 0.5},
       "items": [{"k": 1}, "not an object", {"k": "one"}], "extra": 1}


def test_reads_values_and_notes_every_problem_with_its_path():
    doc = Fields.document(DOC, "f.json")
    doc.known(("a", "items"))
    a = doc.section("a")
    assert a.integer("n", lo=1) == 3
    np.testing.assert_array_equal(a.vector("x"), [1.0, 2.0, 3.0])
    assert a.choice("c", ("linear", "srgb")) == "srgb"
    np.testing.assert_array_equal(a.rgb("rgb"), [0.5, 0.5, 0.5])
    assert a.number("missing", default=2.5) == 2.5
    assert a.number("n", hi=2) is None
    ks = [item.integer("k") for item in doc.items("items")]
    assert ks == [1, None]
    assert doc.section("absent").number("y") is None  # a missing section reads as empty: one problem only
    with pytest.raises(InputErrors) as info:
        doc.problems.check()
    assert info.value.problems == [
        "f.json: extra: unknown field (expected one of: a, items)",
        "f.json: a.n: must be <= 2, got 3",
        "f.json: items[1]: expected an object",
        "f.json: items[2].k: expected an integer, got 'one'",
        "f.json: absent: missing field",
    ]


def test_not_an_object_at_the_top():
    doc = Fields.document([1, 2], "f.json")
    assert doc.number("x") is None
    with pytest.raises(InputErrors, match="f.json: expected a JSON object"):
        doc.problems.check()


def test_problems_stop_at_their_limit():
    problems = Problems(limit=5)
    with pytest.raises(InputErrors) as info:
        for i in range(10**6):
            problems.add(f"line {i}")
    assert info.value.problems == [f"line {i}" for i in range(5)] + ["... stopped after 5 problems"]
