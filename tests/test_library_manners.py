"""The library's manners in a process of its own: importing and using every package changes no JAX configuration
and no environment variable (the command line owns its process and sets both; the library leaves them to its
caller), and nothing is printed, at interpreter exit included (a solver's native object released by its owner)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = """
import json, os
import jax

def configuration():
    return {name: repr(getattr(jax.config, name, None)) for name in jax.config.values}

jax.config.update("jax_enable_x64", True)  # the caller's choice, made before the library is imported
config, environment = configuration(), dict(os.environ)
import numpy as np
import cutting, deform, jaxcga, xfem

arm = deform.default_arm()
deform.skin_model(arm, 0.5)  # a checked entry point
V, F = np.asarray(arm.mesh.V), np.asarray(arm.mesh.F)
data = deform.arap_precompute(V, F, np.arange(3))  # a CHOLMOD factor, solved from compiled code
deform.arap_solve(data, V[:3], max_iterations=3)
field = deform.ffd_precompute(V, deform.bounding_lattice(V, (2, 2, 2)))
deform.motor_field_solve(field, jaxcga.Multivector(np.tile([1.0, 0, 0, 0, 0, 0, 0, 0], (8, 1)), jaxcga.KINDS["motor"]))
changed = {k: v for k, v in configuration().items() if config[k] != v}
moved = sorted(set(os.environ.items()) ^ set(environment.items()))
print(json.dumps({"config": changed, "environment": moved}))
"""


def test_the_library_changes_no_jax_configuration_or_environment_and_prints_nothing_at_exit():
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(SCRIPT)], cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads(done.stdout) == {"config": {}, "environment": []}
    assert done.stderr == ""  # e.g. no "nanobind: leaked 1 instances!" from a solver held until exit
