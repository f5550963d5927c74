"""The child process of ``_jaxcga_shared.tetmeshing.ftetwild``, run as a script in a private temporary folder:
fTetWild (``wildmeshing``) reads ``input.npz`` there and writes ``output.npz``. It imports nothing of this
distribution, so it starts in a fraction of a second."""

import numpy as np
import wildmeshing

with np.load("input.npz") as arrays:
    V, F, options = arrays["V"], arrays["F"], arrays["options"]
edge_length, epsilon, stop_quality, max_iterations, threads = options.tolist()
mesher = wildmeshing.Tetrahedralizer(
    stop_quality=stop_quality,
    max_its=int(max_iterations),
    epsilon=epsilon,
    edge_length_r=edge_length,
    max_threads=int(threads),
)
mesher.set_log_level(6)
mesher.set_mesh(V, F)
mesher.tetrahedralize()
TV, TT = mesher.get_tet_mesh()[:2]
np.savez("output.npz", TV=TV, TT=TT)
