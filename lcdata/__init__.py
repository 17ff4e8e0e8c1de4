"""lcdata: record simulator episodes to MCAP (protobuf), read them back as pandas DataFrames.

Writing::

    with EpisodeWriter("runs/ep0001.mcap", metadata={"config": cfg, "seed": 1, "driver": "rule"}) as w:
        w.write_vehicles(step, t_s, ids, x, y, yaw, speed, accel, lane, target_lane, length, width)
        w.write_ego(step, t_s, speed=v, lane=k, collision_with=-1)

Recording a simulated episode (any driver loop can attach an ``EpisodeRecorder`` instead)::

    result = record_episode(lcsim.paper_scenario(), seed=1, driver="rule", path="runs/ep0001.mcap")

Offline data first: ``rebuild_observations(episode)`` recomputes what the driver saw at every decision
from the recorded tracks (with the simulator's own ``observe``); ``replay(path)`` re-simulates an episode
from its config, episode seed and actions and reports whether the tracks match bit for bit.

Reading::

    episode = read_episode("runs/ep0001.mcap")
    episode.tracks  # long-form DataFrame, one row per vehicle per step

Regenerate the protobuf module after editing ``lcdata/proto/lc.proto``: ``python tools/gen_protos.py``.
"""

from lcdata.offline import ObservationRebuilder, ReplayReport, rebuild_observations, replay
from lcdata.reader import Episode, TruncatedFileWarning, iter_episodes, list_episodes, read_episode
from lcdata.record import EpisodeRecorder, RecordResult, episode_seed, record_episode
from lcdata.writer import EpisodeWriter, partial_path

__all__ = [
    "Episode",
    "EpisodeRecorder",
    "EpisodeWriter",
    "ObservationRebuilder",
    "RecordResult",
    "ReplayReport",
    "TruncatedFileWarning",
    "episode_seed",
    "iter_episodes",
    "list_episodes",
    "partial_path",
    "read_episode",
    "rebuild_observations",
    "record_episode",
    "replay",
]
