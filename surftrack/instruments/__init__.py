"""Articulated surgical instruments: parts, kinematics, fitting joints to part poses, procedural meshes,
YAML library, BOP models."""

from surftrack.instruments.bop_models import assign_obj_ids, export_bop_models, load_bop_models, model_info
from surftrack.instruments.fit import (FitConfig, JointFit, base_from_root, estimate_trocar, fit_configuration,
                                      joints_from_poses)
from surftrack.instruments.kinematics import (
    JOINT_NAMES,
    JointLimits,
    JointState,
    KinematicChain,
    PartJoint,
    rcm_base_pose,
)
from surftrack.instruments.library import (
    BUILTIN,
    INSTRUMENTS_ENV,
    Attachment,
    Instrument,
    InstrumentError,
    InstrumentRegistry,
    instrument_files,
    list_instruments,
    load_instrument,
    load_instrument_file,
)
from surftrack.instruments.part import Material, Part
from surftrack.instruments.twin import HALF_TURN, RollTwin, find_roll_twin

__all__ = [
    "BUILTIN", "INSTRUMENTS_ENV", "Attachment", "FitConfig", "Instrument", "InstrumentError", "InstrumentRegistry",
    "JOINT_NAMES", "JointFit",
    "HALF_TURN", "JointLimits", "JointState", "KinematicChain", "Material", "Part", "PartJoint", "RollTwin",
    "assign_obj_ids", "estimate_trocar", "export_bop_models", "base_from_root", "find_roll_twin", "fit_configuration",
    "joints_from_poses", "instrument_files", "list_instruments", "load_bop_models",
    "load_instrument", "load_instrument_file", "model_info", "rcm_base_pose",
]
