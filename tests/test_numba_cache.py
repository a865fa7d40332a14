"""The library's numba cache is keyed on all its sources: numba itself only notices an
edit to the file of the function it compiled, not to the files of the compiled functions
that function calls, and would run stale kernels from its cache."""

import os
import subprocess
import sys
from pathlib import Path

import numba
import stance  # noqa: F401 - importing the library points numba's cache
from stance import numba_cache


def test_importing_the_library_points_the_cache_at_its_sources_directory():
    base = os.environ.get("NUMBA_CACHE_DIR") or numba_cache.PACKAGE / "__pycache__"
    assert Path(numba.config.CACHE_DIR) == Path(base) / f"numba-{numba_cache.source_digest()}"


def test_an_edit_to_any_source_changes_the_digest(tmp_path):
    (tmp_path / "callee.py").write_text("def g(x):\n    return x + 1.0\n")
    (tmp_path / "caller.py").write_text("from callee import g\n")
    before = numba_cache.source_digest(tmp_path)
    assert numba_cache.source_digest(tmp_path) == before
    (tmp_path / "callee.py").write_text("def g(x):\n    return x + 100.0\n")
    assert numba_cache.source_digest(tmp_path) != before


def test_directories_of_other_sources_are_removed(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    previous = numba.config.CACHE_DIR
    try:
        (tmp_path / "numba-0000000000000000").mkdir()
        directory = numba_cache.use_source_keyed_cache()
        assert directory.parent == tmp_path and numba.config.CACHE_DIR == str(directory)
        assert not (tmp_path / "numba-0000000000000000").exists()
    finally:
        numba.config.CACHE_DIR = previous


# In a fresh process after `stance compile`: pik_node's warm-up in every configuration the
# command compiles by default, then the number of signatures the library's kernels compiled
# instead of loading from the cache.
FRESH_PROCESS_MISSES = """
import sys
import numba.core.registry
from stance_tools.warm_cache import configurations, warm
for robot_name, limits_file, hierarchy in configurations():
    warm(robot_name, hierarchy, limits_file)
kernels = [value for module in list(sys.modules.values())
           if (getattr(module, "__name__", "") or "").startswith("stance.")
           for value in vars(module).values()
           if isinstance(value, numba.core.registry.CPUDispatcher)]
print(sum(sum(kernel.stats.cache_misses.values()) for kernel in kernels), len(kernels))
"""


def test_stance_compile_leaves_nothing_for_pik_node_to_compile():
    # make setup runs `stance compile`; run it again so the test holds on its own
    subprocess.run([sys.executable, "-m", "stance_tools.cli", "compile"], check=True,
                   capture_output=True, timeout=600)
    result = subprocess.run([sys.executable, "-c", FRESH_PROCESS_MISSES], check=True,
                            capture_output=True, text=True, timeout=120)
    misses, kernels = map(int, result.stdout.split()[-2:])
    assert kernels > 20   # the count sees the library's kernels
    assert misses == 0


def test_stance_compile_covers_the_configurations_talos_ships():
    from stance_tools.warm_cache import configurations, shipped_limit_files

    # Talos: no limit file of its own, its hips and shoulders in the shipped `talos` file
    assert configurations() == [("talos", limits, hierarchy) for limits in ("", "talos")
                                for hierarchy in ("svd", "qp")]
    assert shipped_limit_files("mannequin") == [""]   # its own file is the shipped one
