"""The journal's rate limiter, shared by the problem journal and the sensor threads' warnings."""

from __future__ import annotations

from logger.runtime.journal import RateLimiter, problem_key


def test_a_problem_is_the_same_problem_whatever_its_numbers() -> None:
    assert problem_key("no sample for 4.2 s") == problem_key("no sample for 17 s")
    assert problem_key("imu: no sample") != problem_key("baro: no sample")


def test_held_back_lines_are_counted_per_key() -> None:
    lim = RateLimiter(burst=1, refill_s=60.0)
    assert lim.allow("a", 0.0) == (True, 0)
    assert lim.allow("a", 1.0) == (False, 0)
    assert lim.allow("a", 2.0) == (False, 0)
    assert lim.allow("b", 3.0) == (True, 0)  # b's first line carries none of a's repeats
    assert lim.allow("a", 61.0) == (True, 2)  # a's next line says how many of a were held back
    assert lim.allow("b", 64.0) == (True, 0)


def test_burst_then_one_per_refill() -> None:
    lim = RateLimiter(burst=3, refill_s=10.0)
    assert [lim.allow("k", 0.0)[0] for _ in range(4)] == [True, True, True, False]
    assert lim.allow("k", 5.0)[0] is False  # half a token back
    assert lim.allow("k", 10.0) == (True, 2)  # a whole token back: the two refused lines are reported


def test_prune_forgets_refilled_buckets_first_then_all_but_the_kept() -> None:
    lim = RateLimiter(burst=1, refill_s=10.0, max_keys=2)
    lim.allow("old", 0.0)
    lim.allow("recent", 95.0)
    lim.allow("flapping", 99.0)
    lim.allow("flapping", 99.5)  # held back
    lim.prune(100.0)  # "old" has refilled (a line of it would go out anyway): only it is forgotten
    assert lim.allow("flapping", 100.0) == (False, 0)  # still limited: its bucket was kept
    assert lim.allow("old", 100.0) == (True, 0)
    lim.allow("third", 100.0)
    lim.prune(100.0, keep={"third"})  # nothing has refilled: everything but the kept goes
    assert lim.allow("third", 100.0) == (False, 0)
    assert lim.allow("flapping", 100.0) == (True, 0)  # forgotten, with its held-back count
