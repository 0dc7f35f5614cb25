"""Real time: the online engine and its Lab Streaming Layer (LSL) adapters.

* :class:`Engine` (:mod:`.engine`): causal, sample-by-sample fusion of asynchronous IMU and
  camera streams, one output per camera frame, with fault handling and checkpoints;
  :func:`offline_causal` (:mod:`.offline`) runs the same per-frame code (:mod:`.alignment`) on
  a recording.
* Processors (:mod:`.processors`): :class:`KalmanFusionProcessor` (IMU + camera KF baseline),
  :class:`IntegratedProcessor` (paper A's EM-KF/FIR); the :class:`Processor` protocol.
* LSL (:mod:`.lsl`, :mod:`.replay`, :mod:`.runner`, :mod:`.loop`): :func:`run_replay`
  publishes a recording as LSL streams (:class:`ReplaySummary`), :func:`run_stream` runs the
  engine on LSL inlets and publishes the fused joints (:class:`StreamSummary`). pylsl is
  imported lazily and only after :func:`ensure_local_lsl_config` has pointed ``LSLAPICFG`` at
  a machine-local configuration (:mod:`.config`).
"""

from kinefuse.streaming.config import (
    LslUnavailable,
    StreamConfig,
    ensure_local_lsl_config,
    import_pylsl,
    load_stream_config,
)
from kinefuse.streaming.engine import (
    Engine,
    EngineConfig,
    EngineEvent,
    EngineOutput,
)
from kinefuse.streaming.offline import OfflineCausalResult, offline_causal
from kinefuse.streaming.processors import (
    SOURCE_PREDICT,
    IntegratedProcessor,
    KalmanFusionProcessor,
    Processor,
)
from kinefuse.streaming.replay import ReplaySummary, run_replay
from kinefuse.streaming.runner import StreamSummary, run_stream

#: Alias used by :mod:`kinefuse.cli` (``kinefuse replay RECORDING``).
replay_recording = run_replay

__all__ = [
    "SOURCE_PREDICT",
    "Engine",
    "EngineConfig",
    "EngineEvent",
    "EngineOutput",
    "IntegratedProcessor",
    "KalmanFusionProcessor",
    "LslUnavailable",
    "OfflineCausalResult",
    "Processor",
    "ReplaySummary",
    "StreamConfig",
    "StreamSummary",
    "ensure_local_lsl_config",
    "import_pylsl",
    "load_stream_config",
    "offline_causal",
    "replay_recording",
    "run_replay",
    "run_stream",
]
