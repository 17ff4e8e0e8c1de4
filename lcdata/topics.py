"""Topic names and their schemas: one topic per stream, one schema per topic."""

from __future__ import annotations

from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.message import Message

from lcdata.proto import lc_pb2

VEHICLES = "/vehicles"
EGO_STATE = "/ego/state"
EGO_COLLISION = "/ego/collision"
CAMERA_BEV = "/camera/bev_semantic"
TF = "/tf"
SCENE = "/scene"
LOG = "/log"
RL_STEP = "/rl/step"
PREDICTION = "/prediction"
PLANNER_DECISION = "/planner/decision"

#: topic -> protobuf message class written on it.
TOPIC_TYPES: dict[str, type[Message]] = {
    VEHICLES: lc_pb2.VehicleTracks,
    EGO_STATE: lc_pb2.EgoState,
    EGO_COLLISION: lc_pb2.EgoCollision,
    CAMERA_BEV: RawImage,
    TF: FrameTransform,
    SCENE: SceneUpdate,
    LOG: Log,
    RL_STEP: lc_pb2.RLStep,
    PREDICTION: lc_pb2.Prediction,
    PLANNER_DECISION: lc_pb2.PlannerDecision,
}

#: fully qualified schema name -> message class, for the reader.
SCHEMA_TYPES: dict[str, type[Message]] = {cls.DESCRIPTOR.full_name: cls for cls in TOPIC_TYPES.values()}

#: name of the MCAP metadata record holding the episode description.
METADATA_NAME = "lc"

#: world and ego frame ids used in /tf, /scene and the image.
WORLD_FRAME = "world"
EGO_FRAME = "ego"
