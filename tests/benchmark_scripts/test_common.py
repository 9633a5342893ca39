"""benchmarks/common.py: what every benchmark's JSON records about the machine, alternating timings."""

from importlib import metadata

from benchmarks.common import alternating, environment


def test_environment_records_the_processor_and_the_solver_versions():
    env = environment()
    assert env["cpus"] >= 1 and isinstance(env["cpu_model"], str) and env["cpu_model"]
    assert env["packages"]["numpy"] == metadata.version("numpy")
    assert env["packages"]["jaxlib"] == metadata.version("jaxlib")
    assert set(env["packages"]) >= {"highspy", "clarabel", "scipy"}


def test_alternating_runs_every_call_once_per_round_in_turn():
    order = []
    calls = {name: (lambda name=name: order.append(name)) for name in ("a", "b")}
    times = alternating(calls, 3)
    assert order == ["a", "b"] * 3
    assert set(times) == {"a", "b"} and all(len(t) == 3 and min(t) >= 0 for t in times.values())
    assert [len(t) for t in alternating(calls, 0).values()] == [1, 1]  # at least one round
