"""Parameter sweeps: vmapped, sharded over (forced) host devices, equal to a Python loop."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from scenes import block_spec

from jaxmpm.errors import JaxmpmError
from jaxmpm.scene import load_scene
from jaxmpm.sweep import sweep, sweep_params

SCRIPT = textwrap.dedent(
    """
    import json, sys
    import jax, jax.numpy as jnp, numpy as np
    sys.path.insert(0, {tests!r})
    from scenes import block_spec
    from jaxmpm.identify import set_param
    from jaxmpm.scene import load_scene
    from jaxmpm.step import simulate
    from jaxmpm.sweep import sweep

    assert len(jax.devices()) == 4, jax.devices()
    floor = {{"point": [0.0, 0.1], "normal": [0.0, 1.0], "contact": "sticky"}}
    scene = load_scene(block_spec(2, dx=0.1, frames=3, substeps=10, floor=floor))
    mus = [1.0, 10.0, 100.0, 300.0, 3.0, 30.0]          # 6 sets: padded to 8 over 4 devices
    vels = [[0.1 * i, -0.2 * i] for i in range(6)]
    fn = lambda traj: {{"front": traj.x[-1, :, 0].max(), "y": traj.x[-1, :, 1]}}
    out = sweep(scene.model, scene.params, {{"mu": mus, "velocity": vels}}, fn=fn)
    chunked = sweep(scene.model, scene.params, {{"mu": mus, "velocity": vels}}, fn=fn, batch_size=1)
    worst = 0.0
    reference = jax.jit(lambda p: fn(simulate(scene.model, p, checkpoint=None)))
    for i, (mu, v) in enumerate(zip(mus, vels)):
        p = set_param(scene.params, ("bodies", 0, "mu"), jnp.asarray(mu, jnp.float32))
        p = set_param(p, ("bodies", 0, "velocity"), jnp.asarray(v, jnp.float32))
        ref = reference(p)
        for key in ("front", "y"):
            worst = max(worst, float(np.max(np.abs(np.asarray(ref[key]) - out[key][i]))),
                        float(np.max(np.abs(np.asarray(ref[key]) - chunked[key][i]))))
    print("SWEEP", json.dumps({{"shape": list(out["y"].shape), "worst": worst,
                                "devices": len(jax.devices())}}))
    """
)


def test_sweep_over_four_host_devices_equals_a_loop():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    tests = str(Path(__file__).parent)
    proc = subprocess.run([sys.executable, "-c", SCRIPT.format(tests=tests)], capture_output=True, text=True,
                          env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = next(line for line in proc.stdout.splitlines() if line.startswith("SWEEP "))
    import json

    out = json.loads(line[len("SWEEP "):])
    assert out["devices"] == 4
    assert out["shape"][0] == 6  # the padding is removed
    assert out["worst"] <= 1e-6


def test_sweep_product_and_errors():
    scene = load_scene(block_spec(2, dx=0.1, frames=2, substeps=5))
    values, B = sweep_params(scene.model, scene.params, {"mu": [1.0, 2.0], "kappa": [1e3, 1e4, 1e5]}, product=True)
    assert B == 6 and values["mu"].tolist() == [1.0] * 3 + [2.0] * 3
    with pytest.raises(JaxmpmError, match="same length"):
        sweep_params(scene.model, scene.params, {"mu": [1.0, 2.0], "kappa": [1e3]})
    with pytest.raises(JaxmpmError, match="unknown parameter 'E'"):
        sweep(scene.model, scene.params, {"E": [1.0]})
    with pytest.raises(JaxmpmError, match=r"shape \(B,\) \+ \(2,\)"):
        sweep_params(scene.model, scene.params, {"velocity": [1.0, 2.0]})
    with pytest.raises(JaxmpmError, match="at least one"):
        sweep_params(scene.model, scene.params, {})
    # one device here: the default fn returns the positions of every set
    x = sweep(scene.model, scene.params, {"mu": [1.0, 5.0, 9.0]})
    assert x.shape == (3, 2, scene.model.num_particles, 2) and np.all(np.isfinite(x))
