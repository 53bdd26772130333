"""Design stage: the parametric BIP (:class:`BIPDesign`) and its tagged tetra mesh (:class:`PhantomModel`)."""

from softphantom.design.params import (
    ARM_NAMES,
    CAVITY_NAMES,
    ArmParams,
    BIPDesign,
    BulbParams,
    CapsuleCavity,
    EllipsoidCavity,
    InteractionParams,
    MeshParams,
    SensorParams,
    UrethraParams,
    design_from_dict,
    design_to_dict,
    load_design,
    save_design,
)
from softphantom.design.model import PhantomModel, build_model, default_design, load_model, save_model, shipped_model


__all__ = [
    "ARM_NAMES",
    "CAVITY_NAMES",
    "ArmParams",
    "BIPDesign",
    "BulbParams",
    "CapsuleCavity",
    "EllipsoidCavity",
    "InteractionParams",
    "MeshParams",
    "SensorParams",
    "UrethraParams",
    "design_from_dict",
    "design_to_dict",
    "load_design",
    "save_design",
    "PhantomModel",
    "build_model",
    "default_design",
    "shipped_model",
    "load_model",
    "save_model",
]
