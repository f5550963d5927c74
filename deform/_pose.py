"""Posing a rigged model: local transforms -> forward kinematics -> joint transforms -> skinning.

The glue between the rig (``_rig``) and the skinning equations (``_skinning``). A pose is the
local transform of every bone, either as versors (a Multivector with batch shape (..., b), motors
or similitudes) or as matrices (..., b, 4, 4). Methods:

* ``"lbs"``: matrix linear blend skinning, eq. (16);
* ``"dqs"``: dual-quaternion skinning (rigid poses only);
* ``"cga"``: multivector skinning, eq. (17), blend after the sandwich (the paper's), each sandwiched
  point down-projected before the sum as in the paper's implementation (sec. 4.3; ``skin_cga``);
* ``"cga_motor_blend"``: multivector skinning with the versors blended first (like DQS).

``skin_model(model, t)`` samples clip ``clip`` at time t; how keys are interpolated is its own choice,
orthogonal to the method (``interpolation``):

* ``"gltf"`` (the default, for every method): the glTF specification's interpolation (translation and
  scale lerped, rotation slerped, STEP, CUBICSPLINE; ``_rig.sample_trs``), the file's animation as
  three.js and Blender play it. The multivector methods turn the sampled TRS into similitudes
  (``_rig.trs_to_versor``: a non-uniform scale has no versor and raises);
* ``"log"``: the paper's sampling (sec. 4.1 with sec. 2.5): each channel's keys become versors blended
  logarithmically (``_rig.sample_versors``). It equals the specification for translations and
  rotations and differs for scale keys (geometric instead of linear between keys). The matrix methods
  take the log-blended similitudes as matrices (``jaxcga.versor_to_matrix``), so a non-uniform scale
  raises there too.

The model-level functions are compiled on first use (``eqx.filter_jit``: arrays traced, the method name and the
model's static fields part of the cache key), their value checks returned as outputs and raised on the host (no host
callback in the executable: JAX's persistent cache can keep it); inside an outer jit they are inlined.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

import jaxcga as cga
from _jaxcga_shared.checks import check_choice, checked_jit, plain_errors
from deform import _rig, _skinning
from deform._model import RiggedModel
from jaxcga._multivector import Multivector

METHODS = ("lbs", "dqs", "cga", "cga_motor_blend")
INTERPOLATIONS = ("gltf", "log")


@checked_jit
def skin_pose(
    model: RiggedModel, local: Multivector | Float[ArrayLike, "... b 4 4"], method: str = "cga"
) -> Float[Array, "... n 3"]:
    """Skinned positions (..., n, 3) of the model in a pose given by local bone transforms.

    Args:
        model: the RiggedModel.
        local: local transform of every bone: versors (Multivector, batch shape (..., b)) or
            matrices (..., b, 4, 4).
        method: one of ``METHODS``.

    Returns:
        (..., n, 3) the skinned positions.
    """
    check_choice("method", method, METHODS)
    mesh = model.mesh
    joint_bones = jnp.asarray(mesh.joints, jnp.int32)
    return skin_local(model.skeleton.parents, joint_bones, mesh.inverse_bind, mesh.V, mesh.J, mesh.W, local, method)


def skin_local(parents, joint_bones, inverse_bind, V, J, W, local, method: str):
    """``skin_pose`` from the rig as arrays (``joint_transforms``' and ``skin_with_joints``' arguments): local
    versors are turned into matrices for the matrix methods and back. Shared with the packed fits
    (``deform.fit_packed``)."""
    local = local_for_method(local, method)
    return skin_with_joints(V, J, W, joint_transforms(parents, joint_bones, inverse_bind, local), method)


def local_for_method(local, method: str):
    """Local transforms in the form ``method`` skins with: versors for the multivector methods, matrices for the
    matrix methods."""
    if isinstance(local, Multivector) and method not in ("cga", "cga_motor_blend"):
        return cga.versor_to_matrix(local)
    if not isinstance(local, Multivector) and method in ("cga", "cga_motor_blend"):
        return cga.matrix_to_similitude(jnp.asarray(local))
    return local


def joint_transforms(parents, joint_bones, inverse_bind, local):
    """Joint versors ``M_n B_n`` of local versors (the multivector methods) or joint matrices of local matrices:
    forward kinematics over ``parents`` (a tuple or an int array), then the joints' bones (j,) times their inverse
    bind matrices (j, 4, 4). ``skin_pose`` and the packed batches (``deform.skin_packed``) share it."""
    if isinstance(local, Multivector):
        globals_ = _rig.forward_kinematics(parents, local)
        return _rig.joint_versors_of(joint_bones, cga.matrix_to_similitude(inverse_bind), globals_)
    return _rig.joint_matrices_of(joint_bones, inverse_bind, _rig.forward_kinematics_matrices(parents, local))


def skin_with_joints(V, J, W, joints, method: str):
    """Skinned positions from joint transforms (``joint_transforms``) by ``method``."""
    if method == "cga":
        return _skinning.skin_cga(V, J, W, joints)
    if method == "cga_motor_blend":
        return _skinning.skin_cga_motor_blend(V, J, W, joints)
    if method == "lbs":
        return _skinning.skin_lbs(V, J, W, joints)
    return _skinning.skin_dqs(V, J, W, _skinning.matrices_to_dual_quaternions(joints))


@checked_jit
def rest_pose(model: RiggedModel, method: str = "cga") -> Float[Array, "n 3"]:
    """Skinned positions (n, 3) in the skeleton's rest pose (the nodes' own TRS).

    Args:
        model: the RiggedModel.
        method: one of ``METHODS``.

    Returns:
        (n, 3) the skinned positions.

    Examples:
        >>> import deform
        >>> deform.rest_pose(deform.default_arm()).shape
        (3266, 3)
    """
    check_choice("method", method, METHODS)
    if method in ("cga", "cga_motor_blend"):
        return skin_pose(model, _rig.local_versors(model.skeleton), method)
    return skin_pose(model, _rig.local_matrices(model.skeleton), method)


@plain_errors
def sample_pose(
    model: RiggedModel,
    t: Float[ArrayLike, ""],
    method: str = "cga",
    clip: int | str = 0,
    interpolation: str = "gltf",
) -> Multivector | Float[Array, "b 4 4"]:
    """Local bone transforms of clip ``clip`` at time t: versors (b,) for the multivector methods,
    matrices (b, 4, 4) for the matrix methods.

    Args:
        model: the RiggedModel.
        t: () time in seconds (clamped to the clip's key range).
        method: one of ``METHODS``: picks the form of the result.
        clip: clip name or index.
        interpolation: ``"gltf"`` (the specification's, default) or ``"log"`` (the paper's
            logarithmic blending of key versors); module docstring.

    Returns:
        Versors, batch shape (b,), or (b, 4, 4) matrices, by ``method``.

    Examples:
        >>> import deform
        >>> arm = deform.default_arm()
        >>> deform.sample_pose(arm, 0.5).batch_shape, deform.sample_pose(arm, 0.5, "lbs").shape  # versors, matrices
        ((4,), (4, 4, 4))
    """
    check_choice("method", method, METHODS)
    check_choice("interpolation", interpolation, INTERPOLATIONS)
    # The time goes in as an array: filter_jit would treat a Python float as static and recompile.
    return _sample_pose(model, jnp.asarray(t), method, model.clip(clip), interpolation)


@checked_jit
def _sample_pose(model: RiggedModel, t, method: str, animation, interpolation: str):
    skeleton = model.skeleton
    rest = (skeleton.translation, skeleton.rotation, skeleton.scale)
    return sample_stacked_pose(rest, _rig.stacked_channels(animation), t, method, interpolation)


def sample_stacked_pose(rest, groups, t, method: str, interpolation: str):
    """``sample_pose`` from a rest TRS and stacked channel groups (``_rig.stacked_channels``): shared with the
    packed batches (``deform.skin_packed``)."""
    if interpolation == "log":
        local = _rig.sample_stacked_versors(rest, groups, t)
        return local if method in ("cga", "cga_motor_blend") else cga.versor_to_matrix(local)
    if method in ("cga", "cga_motor_blend"):
        return _rig.trs_to_versor(*_rig.sample_stacked_trs(rest, groups, t))
    return _rig.trs_to_matrix(*_rig.sample_stacked_trs(rest, groups, t))


@plain_errors
def skin_model(
    model: RiggedModel,
    t: Float[ArrayLike, ""],
    method: str = "cga",
    clip: int | str = 0,
    interpolation: str = "gltf",
) -> Float[Array, "n 3"]:
    """Skinned positions (n, 3) of the model at time t of a clip (rest pose when it has no clip).
    vmap over t for many frames.

    Args:
        model: the RiggedModel.
        t: () time in seconds (clamped to the clip's key range).
        method: one of ``METHODS``.
        clip: clip name or index.
        interpolation: ``"gltf"`` (the specification's, default) or ``"log"`` (the paper's); module
            docstring.

    Returns:
        (n, 3) the skinned positions.

    Examples:
        >>> import jax, jax.numpy as jnp
        >>> import deform
        >>> arm = deform.default_arm()  # the built-in rigged arm: 4 bones, one clip
        >>> deform.skin_model(arm, 0.5, "cga").shape  # (n, 3) at t = 0.5 s
        (3266, 3)
        >>> jax.vmap(lambda t: deform.skin_model(arm, t, "lbs"))(jnp.linspace(0.0, 1.0, 5)).shape  # many frames
        (5, 3266, 3)
    """
    check_choice("method", method, METHODS)
    check_choice("interpolation", interpolation, INTERPOLATIONS)
    if not model.clips:
        return rest_pose(model, method)
    return _skin_model(model, jnp.asarray(t), method, model.clip(clip), interpolation)


@checked_jit
def _skin_model(model: RiggedModel, t, method: str, animation, interpolation: str):
    return skin_pose(model, _sample_pose(model, t, method, animation, interpolation), method)
