"""Test configuration: strict dtype promotion, and float32 (what users run) unless a test opts in.

A test that needs float64 (finite differences, tight references) says so with
``@pytest.mark.x64`` (or ``pytestmark = pytest.mark.x64`` for a whole file): x64 is then on
for that test's setup, call and teardown only (``jax.enable_x64`` is a scoped context).

Compiled programs go to a persistent compilation cache of this run only (a fresh folder,
shared by the xdist workers and the commands the tests start, removed at the end): a
program compiled by one test is loaded by the next that needs it, and nothing is kept
between runs or read from the user's cache. The xdist workers read it but do not write it:
in two CI runs of session 23 a worker aborted inside XLA's serialisation of an executable
for the cache (``executable.serialize()``, the same test both times, at 91 % of the run;
the test alone, writing its programs, passes), so only the commands the tests
start and a run without xdist write entries.
"""

import os
import shutil
import tempfile

# XLA's CPU fusion emitters (its default) spend 1.3-2x longer compiling this project's programs
# than its classic emitters, and a test here is mostly compilation: the suite compiles with the
# classic ones (same arithmetic, other fusion and rounding order; docs/benchmarks.md, session 37).
# Set before JAX starts its CPU client; the commands the tests start inherit it.
# XLA_FLAGS=--xla_cpu_use_fusion_emitters=true runs the suite on XLA's default instead.
if "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_use_fusion_emitters=false").strip()

import jax  # noqa: E402  (after XLA_FLAGS)
import pytest

from jaxmpm.cache import CACHE_ENV

jax.config.update("jax_numpy_dtype_promotion", "strict")


def pytest_configure(config):
    if not hasattr(config, "workerinput"):  # the controller (or a run without xdist): this run's folder
        config._jaxmpm_cache = os.environ[CACHE_ENV] = tempfile.mkdtemp(prefix="jaxmpm-test-xla-")
    jax.config.update("jax_compilation_cache_dir", os.environ[CACHE_ENV])  # this run's, whatever JAX's env says
    if hasattr(config, "workerinput"):  # an xdist worker: read the cache, never write it (see above)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", float("inf"))
    config.addinivalue_line("markers", "x64: run this test with float64 enabled (jax.enable_x64), scoped to the test")
    # without x64 a float64 request silently gives float32: make it an error, so a test that
    # needs float64 and lacks the marker fails instead of passing on weaker arithmetic
    config.addinivalue_line("filterwarnings", "error:Explicitly requested dtype.*float64:UserWarning")


def pytest_unconfigure(config):
    folder = getattr(config, "_jaxmpm_cache", None)
    if folder:
        shutil.rmtree(folder, ignore_errors=True)


#: Modules whose tests share work: a module-scoped fixture (a rendered dataset, a simulated
#: observation) or compiled programs (the same scene rolled out, screened or fitted by several
#: tests). Under xdist each runs whole on one worker, so that the fixture is built once and
#: the programs compile once; spread over both workers, each worker built and compiled its
#: own copy (docs/benchmarks.md, session 38).
SHARED_WORK_MODULES = (
    "test_cli.py", "test_discover.py", "test_fit_images.py", "test_fit_losses.py", "test_fit_methods.py",
    "test_reconstruct.py",
)


def pytest_xdist_make_scheduler(config, log):
    """xdist's ``load`` distribution, with each of :data:`SHARED_WORK_MODULES` one unit of work.

    (xdist's own ``--dist loadgroup`` does not group on pytest 9.2: pytest-xdist issue 1386.)
    Other ``--dist`` modes are left as xdist makes them."""
    if config.getvalue("dist") != "load":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class SharedWorkScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            module = nodeid.split("::", 1)[0]
            return module if module.rsplit("/", 1)[-1] in SHARED_WORK_MODULES else nodeid

    return SharedWorkScheduling(config, log)


@pytest.fixture(autouse=True)
def _x64_when_marked(request):
    """Enable x64 around a test marked ``x64``; leave the float32 default otherwise."""
    if request.node.get_closest_marker("x64") is None:
        yield
        return
    with jax.enable_x64(True):
        yield


@pytest.fixture(params=[2, 3], ids=["2d", "3d"])
def dim(request):
    return request.param
