"""benchmarks/common.py: what every benchmark's JSON records about the machine."""

from importlib import metadata

from benchmarks.common import environment


def test_environment_records_the_processor_and_the_solver_versions():
    env = environment()
    assert env["cpus"] >= 1 and isinstance(env["cpu_model"], str) and env["cpu_model"]
    assert env["packages"]["numpy"] == metadata.version("numpy")
    assert env["packages"]["jaxlib"] == metadata.version("jaxlib")
    assert set(env["packages"]) >= {"highspy", "clarabel", "scipy"}
