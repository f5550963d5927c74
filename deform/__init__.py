"""deform: rigged models (glTF/FBX I/O, skeletons, clips, skinning) on the jaxcga kernel.

Sections 3 and 4.1 of the cut/tear/drill paper: the rigged deformation equation (16) and its
multivector form (17) with per-bone dilation, keyframe blending, and fitting poses to targets.

Where things live: ``_model`` (bundles), ``_rig`` (TRS -> matrices / versors, forward kinematics,
clip sampling, keyframes; eq. 15), ``_skinning`` (eq. 16, eq. 17 in both variants, DQS), ``_pose``
(model-level posing, batches over devices), ``_fitting`` (poses from target positions); from the
mesh-deformation paper: ``_harmonic`` (harmonic fields, sec. VIII) on ``_sparse`` (a sparse system
factored once on the host and solved from JAX).
"""

from deform._default_arm import default_arm
from deform._fitting import (
    PARAMETERS_PER_BONE,
    SOLVERS,
    PoseFit,
    bounding_diagonal,
    fit_pose,
    pose_from_parameters,
    random_parameters,
    skin_parameters,
)
from deform._gltf import convert_with_assimp, load_model, save_model, weld
from deform._harmonic import (LAPLACIANS, HarmonicSolver, harmonic_fields, harmonic_precompute, laplacian,
                              mean_value_laplacian)
from deform._model import AnimationClip, Channel, RiggedModel, Skeleton, SkinnedMesh
from deform._pose import METHODS, rest_pose, sample_pose, sharded_vmap, skin_model, skin_pose
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
from deform._sparse import SparseSolver
from deform._skinning import matrices_to_dual_quaternions, skin_cga, skin_cga_motor_blend, skin_dqs, skin_lbs

__all__ = [
    "LAPLACIANS",
    "HarmonicSolver",
    "SparseSolver",
    "harmonic_fields",
    "harmonic_precompute",
    "laplacian",
    "mean_value_laplacian",
    "METHODS",
    "PARAMETERS_PER_BONE",
    "SOLVERS",
    "AnimationClip",
    "Channel",
    "Keyframes",
    "PoseFit",
    "RiggedModel",
    "Skeleton",
    "SkinnedMesh",
    "bounding_diagonal",
    "clip_from_poses",
    "convert_with_assimp",
    "default_arm",
    "fit_pose",
    "forward_kinematics",
    "forward_kinematics_matrices",
    "inverse_bind_versors",
    "joint_matrices",
    "joint_versors",
    "load_model",
    "local_matrices",
    "local_versors",
    "matrices_to_dual_quaternions",
    "pose_from_parameters",
    "quaternion_xyzw_to_matrix",
    "random_parameters",
    "rest_pose",
    "sample_channel",
    "sample_keyframes",
    "sample_matrices",
    "sample_pose",
    "sample_trs",
    "sample_versors",
    "save_model",
    "sharded_vmap",
    "skin_cga",
    "skin_cga_motor_blend",
    "skin_dqs",
    "skin_lbs",
    "skin_model",
    "skin_parameters",
    "skin_pose",
    "trs_to_matrix",
    "trs_to_versor",
    "uniform_scale",
    "versor_to_trs",
    "weld",
]
