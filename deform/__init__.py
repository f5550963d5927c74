"""deform: rigged models (glTF/FBX I/O, skeletons, clips, skinning) on the jaxcga kernel.

Sections 3 and 4.1 of the cut/tear/drill paper: the rigged deformation equation (16) and its
multivector form (17) with per-bone dilation, keyframe blending, and fitting poses to targets.

Where things live: ``_model`` (bundles), ``_rig`` (TRS -> matrices / versors, forward kinematics,
clip sampling, keyframes; eq. 15), ``_skinning`` (eq. 16, eq. 17 in both variants, DQS), ``_pose``
(model-level posing), ``_fitting`` (poses from target positions); from the
mesh-deformation paper: ``_harmonic`` (harmonic fields, sec. VIII) on ``_jaxcga_shared.sparse`` (sparse
solves from JAX, on the host or the device); ``_motor_field`` (per-vertex ``exp(sum w log R)`` and the
sec. III-A binding, shared by every motor deformation); ``_spline`` (spline-aligned deformation, eq. 1-2),
``_spline_fit`` (B-spline fitting of key motors, eq. 3-5), ``_fabrik`` (FABRIK inverse kinematics, Fig.
5), ``_handles`` (harmonic motor handles, sec. IV), ``_parts`` (a mesh's connected parts: how the parts
without a handle follow the others, for every deformer with handles), ``_ffd`` (classic and motor FFD, eq. 6-8),
``_cage`` (harmonic-coordinate cages, sec. VI); ``_field_fitting`` (key motors from target positions); ``_arap``
(as-rigid-as-possible modeling with rotors, sec. VII); ``_batch`` (batches of different models packed to shared
capacities, skinned under one jit and split over devices and processes); ``_batch_fitting`` (``fit_pose`` on every
model of such a batch at once).

One convention for every deformer: ``X_precompute(V, F, constraints, *, options) -> data`` (an ``eqx.Module``;
mesh first, ``laplacian=`` where a Laplacian is chosen) does the work that does not depend on the handle
values, and ``X_solve(data, values)`` is a JAX function of them (jit, vmap, grad): ``harmonic_``,
``arap_``, ``spline_fit_``; the motor deformations (``spline_``, ``handles_``, ``ffd_``, ``cage_precompute``
and the general ``motor_field_precompute``) all return a ``MotorField``, solved by ``motor_field_solve``.

``view`` / ``View``: the interactive viewer of glTF models with their clips, mesh sequences (skinned or simulated
frames) and meshes, one self-contained HTML page (three.js in the browser, inline in notebooks).
"""

from typing import TYPE_CHECKING

from _jaxcga_shared.lazy import lazy_exports

# each public name is imported from its module on first use (a command that skins does not import libigl,
# optax or the viewer); type checkers and the documentation read these imports as they are
if TYPE_CHECKING:
    from _jaxcga_shared.viewer import View, view
    from deform._arap import ACCELERATIONS as ARAP_ACCELERATIONS
    from deform._arap import ENERGIES as ARAP_ENERGIES
    from deform._arap import ARAPData, ARAPResult, arap_precompute, arap_solve, horn_rotors
    from deform._arap import default_tolerance as default_arap_tolerance
    from deform._batch import Capacities, PackedModels, PackedRigs, capacity, pack_models, skin_packed
    from deform._batch_fitting import fit_packed
    from deform._cage import cage_precompute, harmonic_coordinates, tube_cage
    from deform._default_arm import default_arm
    from deform._fabrik import chain_motors, fabrik, rotor_between
    from deform._ffd import (
        Lattice,
        bounding_lattice,
        distortion,
        ffd_precompute,
        ffd_weights,
        lattice_coordinates,
        lattice_points,
        twist_lattice,
    )
    from deform._field_fitting import MotorFit, fit_key_motors, generators_to_motors
    from deform._fitting import (
        PARAMETERS_PER_BONE,
        SOLVERS,
        PoseFit,
        fit_pose,
        pose_from_parameters,
        random_parameters,
        skin_parameters,
    )
    from deform._gltf import convert_with_assimp, load_model, save_model, save_models, weld
    from deform._gltf_write import GLTF_OUTPUTS, buffer_file
    from deform._handles import handles_precompute
    from deform._harmonic import (
        LAPLACIANS,
        HarmonicData,
        harmonic_fields,
        harmonic_precompute,
        harmonic_solve,
        laplacian,
        mean_value_laplacian,
    )
    from deform._model import AnimationClip, Channel, RiggedModel, Skeleton, SkinnedMesh
    from deform._motor_field import (
        MotorField,
        blend_motors,
        blend_positions,
        identity_motors,
        motor_about,
        motor_field_precompute,
        motor_field_solve,
        motor_logs,
    )
    from deform._parts import UNHANDLED, MeshParts, mesh_parts
    from deform._pose import (
        INTERPOLATIONS,
        METHODS,
        rest_pose,
        sample_pose,
        skin_model,
        skin_pose,
    )
    from deform._rig import (
        Keyframes,
        clip_from_poses,
        forward_kinematics,
        forward_kinematics_matrices,
        inverse_bind_versors,
        joint_matrices,
        joint_versors,
        local_matrices,
        local_versors,
        quaternion_xyzw_to_matrix,
        sample_channel,
        sample_keyframes,
        sample_matrices,
        sample_trs,
        sample_versors,
        trs_to_matrix,
        trs_to_versor,
        uniform_scale,
        versor_to_trs,
    )
    from deform._skinning import (
        matrices_to_dual_quaternions,
        skin_cga,
        skin_cga_motor_blend,
        skin_dqs,
        skin_lbs,
    )
    from deform._spline import (
        BASES,
        clamped_knots,
        spline_parameter,
        spline_precompute,
        spline_weights,
    )
    from deform._spline_fit import SplineFitData, spline_fit_precompute, spline_fit_solve

__getattr__, __dir__ = lazy_exports(__name__, __file__)

__all__ = [
    "ARAP_ACCELERATIONS",
    "ARAP_ENERGIES",
    "BASES",
    "GLTF_OUTPUTS",
    "LAPLACIANS",
    "INTERPOLATIONS",
    "METHODS",
    "PARAMETERS_PER_BONE",
    "SOLVERS",
    "UNHANDLED",
    "View",
    "ARAPData",
    "ARAPResult",
    "AnimationClip",
    "Capacities",
    "Channel",
    "HarmonicData",
    "Keyframes",
    "Lattice",
    "MeshParts",
    "MotorField",
    "MotorFit",
    "PackedModels",
    "PackedRigs",
    "PoseFit",
    "RiggedModel",
    "Skeleton",
    "SkinnedMesh",
    "SplineFitData",
    "arap_precompute",
    "arap_solve",
    "default_arap_tolerance",
    "blend_motors",
    "blend_positions",
    "bounding_lattice",
    "buffer_file",
    "cage_precompute",
    "capacity",
    "chain_motors",
    "clamped_knots",
    "clip_from_poses",
    "convert_with_assimp",
    "default_arm",
    "distortion",
    "fabrik",
    "ffd_precompute",
    "ffd_weights",
    "fit_key_motors",
    "fit_packed",
    "fit_pose",
    "forward_kinematics",
    "forward_kinematics_matrices",
    "generators_to_motors",
    "handles_precompute",
    "harmonic_coordinates",
    "horn_rotors",
    "harmonic_fields",
    "harmonic_precompute",
    "harmonic_solve",
    "identity_motors",
    "inverse_bind_versors",
    "joint_matrices",
    "joint_versors",
    "laplacian",
    "lattice_coordinates",
    "lattice_points",
    "load_model",
    "local_matrices",
    "local_versors",
    "matrices_to_dual_quaternions",
    "mean_value_laplacian",
    "motor_about",
    "motor_field_precompute",
    "motor_field_solve",
    "mesh_parts",
    "motor_logs",
    "pack_models",
    "pose_from_parameters",
    "quaternion_xyzw_to_matrix",
    "random_parameters",
    "rest_pose",
    "rotor_between",
    "sample_channel",
    "sample_keyframes",
    "sample_matrices",
    "sample_pose",
    "sample_trs",
    "sample_versors",
    "save_model",
    "save_models",
    "skin_cga",
    "skin_cga_motor_blend",
    "skin_dqs",
    "skin_lbs",
    "skin_model",
    "skin_packed",
    "skin_parameters",
    "skin_pose",
    "spline_fit_precompute",
    "spline_fit_solve",
    "spline_parameter",
    "spline_precompute",
    "spline_weights",
    "trs_to_matrix",
    "trs_to_versor",
    "tube_cage",
    "twist_lattice",
    "uniform_scale",
    "versor_to_trs",
    "view",
    "weld",
]
