from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Iterable as _Iterable, Mapping as _Mapping, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class BatchItem(_message.Message):
    __slots__ = ["index"]
    INDEX_FIELD_NUMBER: _ClassVar[int]
    index: int
    def __init__(self, index: _Optional[int] = ...) -> None: ...

class CloseSessionRequest(_message.Message):
    __slots__ = ["session_id"]
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class CloseSessionResponse(_message.Message):
    __slots__ = []
    def __init__(self) -> None: ...

class CreateSessionRequest(_message.Message):
    __slots__ = ["config", "progress", "session_id"]
    CONFIG_FIELD_NUMBER: _ClassVar[int]
    PROGRESS_FIELD_NUMBER: _ClassVar[int]
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    config: SessionConfig
    progress: SessionProgress
    session_id: str
    def __init__(self, session_id: _Optional[str] = ..., config: _Optional[_Union[SessionConfig, _Mapping]] = ..., progress: _Optional[_Union[SessionProgress, _Mapping]] = ...) -> None: ...

class CreateSessionResponse(_message.Message):
    __slots__ = ["session_id"]
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class EndEpisodeRequest(_message.Message):
    __slots__ = ["session_id"]
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class EndEpisodeResponse(_message.Message):
    __slots__ = ["episodes_completed"]
    EPISODES_COMPLETED_FIELD_NUMBER: _ClassVar[int]
    episodes_completed: int
    def __init__(self, episodes_completed: _Optional[int] = ...) -> None: ...

class GetSessionRequest(_message.Message):
    __slots__ = ["session_id"]
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class GetSessionResponse(_message.Message):
    __slots__ = ["config", "episodes_completed", "probe_pending", "response_mean_square", "shift", "step"]
    CONFIG_FIELD_NUMBER: _ClassVar[int]
    EPISODES_COMPLETED_FIELD_NUMBER: _ClassVar[int]
    PROBE_PENDING_FIELD_NUMBER: _ClassVar[int]
    RESPONSE_MEAN_SQUARE_FIELD_NUMBER: _ClassVar[int]
    SHIFT_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    config: SessionConfig
    episodes_completed: int
    probe_pending: bool
    response_mean_square: float
    shift: _containers.RepeatedScalarFieldContainer[float]
    step: int
    def __init__(self, config: _Optional[_Union[SessionConfig, _Mapping]] = ..., step: _Optional[int] = ..., episodes_completed: _Optional[int] = ..., shift: _Optional[_Iterable[float]] = ..., probe_pending: bool = ..., response_mean_square: _Optional[float] = ...) -> None: ...

class ProbeBatchRequest(_message.Message):
    __slots__ = ["action_scales", "actions", "episode_starts", "session_ids", "steps"]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    ACTION_SCALES_FIELD_NUMBER: _ClassVar[int]
    EPISODE_STARTS_FIELD_NUMBER: _ClassVar[int]
    SESSION_IDS_FIELD_NUMBER: _ClassVar[int]
    STEPS_FIELD_NUMBER: _ClassVar[int]
    action_scales: _containers.RepeatedScalarFieldContainer[float]
    actions: _containers.RepeatedScalarFieldContainer[float]
    episode_starts: _containers.RepeatedScalarFieldContainer[bool]
    session_ids: _containers.RepeatedScalarFieldContainer[str]
    steps: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, session_ids: _Optional[_Iterable[str]] = ..., steps: _Optional[_Iterable[int]] = ..., actions: _Optional[_Iterable[float]] = ..., episode_starts: _Optional[_Iterable[bool]] = ..., action_scales: _Optional[_Iterable[float]] = ...) -> None: ...

class ProbeBatchResponse(_message.Message):
    __slots__ = ["actions", "episodes_completed", "probes", "response_mean_squares"]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    EPISODES_COMPLETED_FIELD_NUMBER: _ClassVar[int]
    PROBES_FIELD_NUMBER: _ClassVar[int]
    RESPONSE_MEAN_SQUARES_FIELD_NUMBER: _ClassVar[int]
    actions: _containers.RepeatedScalarFieldContainer[float]
    episodes_completed: _containers.RepeatedScalarFieldContainer[int]
    probes: _containers.RepeatedScalarFieldContainer[float]
    response_mean_squares: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, probes: _Optional[_Iterable[float]] = ..., actions: _Optional[_Iterable[float]] = ..., episodes_completed: _Optional[_Iterable[int]] = ..., response_mean_squares: _Optional[_Iterable[float]] = ...) -> None: ...

class ProbeRequest(_message.Message):
    __slots__ = ["action", "action_scale", "episode_start", "session_id", "step"]
    ACTION_FIELD_NUMBER: _ClassVar[int]
    ACTION_SCALE_FIELD_NUMBER: _ClassVar[int]
    EPISODE_START_FIELD_NUMBER: _ClassVar[int]
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    action: _containers.RepeatedScalarFieldContainer[float]
    action_scale: _containers.RepeatedScalarFieldContainer[float]
    episode_start: bool
    session_id: str
    step: int
    def __init__(self, session_id: _Optional[str] = ..., step: _Optional[int] = ..., action: _Optional[_Iterable[float]] = ..., episode_start: bool = ..., action_scale: _Optional[_Iterable[float]] = ...) -> None: ...

class ProbeResponse(_message.Message):
    __slots__ = ["action", "probe", "step"]
    ACTION_FIELD_NUMBER: _ClassVar[int]
    PROBE_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    action: _containers.RepeatedScalarFieldContainer[float]
    probe: _containers.RepeatedScalarFieldContainer[float]
    step: int
    def __init__(self, probe: _Optional[_Iterable[float]] = ..., step: _Optional[int] = ..., action: _Optional[_Iterable[float]] = ...) -> None: ...

class ReportBatchRequest(_message.Message):
    __slots__ = ["q_references", "q_values", "session_ids", "steps"]
    Q_REFERENCES_FIELD_NUMBER: _ClassVar[int]
    Q_VALUES_FIELD_NUMBER: _ClassVar[int]
    SESSION_IDS_FIELD_NUMBER: _ClassVar[int]
    STEPS_FIELD_NUMBER: _ClassVar[int]
    q_references: _containers.RepeatedScalarFieldContainer[float]
    q_values: _containers.RepeatedScalarFieldContainer[float]
    session_ids: _containers.RepeatedScalarFieldContainer[str]
    steps: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, session_ids: _Optional[_Iterable[str]] = ..., steps: _Optional[_Iterable[int]] = ..., q_values: _Optional[_Iterable[float]] = ..., q_references: _Optional[_Iterable[float]] = ...) -> None: ...

class ReportBatchResponse(_message.Message):
    __slots__ = ["actions"]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    actions: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, actions: _Optional[_Iterable[float]] = ...) -> None: ...

class ReportRequest(_message.Message):
    __slots__ = ["q_reference", "q_value", "session_id", "step"]
    Q_REFERENCE_FIELD_NUMBER: _ClassVar[int]
    Q_VALUE_FIELD_NUMBER: _ClassVar[int]
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    q_reference: float
    q_value: float
    session_id: str
    step: int
    def __init__(self, session_id: _Optional[str] = ..., step: _Optional[int] = ..., q_value: _Optional[float] = ..., q_reference: _Optional[float] = ...) -> None: ...

class ReportResponse(_message.Message):
    __slots__ = ["action", "step"]
    ACTION_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    action: _containers.RepeatedScalarFieldContainer[float]
    step: int
    def __init__(self, action: _Optional[_Iterable[float]] = ..., step: _Optional[int] = ...) -> None: ...

class SessionConfig(_message.Message):
    __slots__ = ["action_dim", "action_high", "action_low", "amplitude", "disable_highpass", "dt", "frequency", "highpass_cutoff", "learning_rate", "lr_decay", "max_episodes", "normalize_response", "response_clip", "response_rms_rate", "shift_leak", "shift_limit", "trust_region"]
    ACTION_DIM_FIELD_NUMBER: _ClassVar[int]
    ACTION_HIGH_FIELD_NUMBER: _ClassVar[int]
    ACTION_LOW_FIELD_NUMBER: _ClassVar[int]
    AMPLITUDE_FIELD_NUMBER: _ClassVar[int]
    DISABLE_HIGHPASS_FIELD_NUMBER: _ClassVar[int]
    DT_FIELD_NUMBER: _ClassVar[int]
    FREQUENCY_FIELD_NUMBER: _ClassVar[int]
    HIGHPASS_CUTOFF_FIELD_NUMBER: _ClassVar[int]
    LEARNING_RATE_FIELD_NUMBER: _ClassVar[int]
    LR_DECAY_FIELD_NUMBER: _ClassVar[int]
    MAX_EPISODES_FIELD_NUMBER: _ClassVar[int]
    NORMALIZE_RESPONSE_FIELD_NUMBER: _ClassVar[int]
    RESPONSE_CLIP_FIELD_NUMBER: _ClassVar[int]
    RESPONSE_RMS_RATE_FIELD_NUMBER: _ClassVar[int]
    SHIFT_LEAK_FIELD_NUMBER: _ClassVar[int]
    SHIFT_LIMIT_FIELD_NUMBER: _ClassVar[int]
    TRUST_REGION_FIELD_NUMBER: _ClassVar[int]
    action_dim: int
    action_high: _containers.RepeatedScalarFieldContainer[float]
    action_low: _containers.RepeatedScalarFieldContainer[float]
    amplitude: _containers.RepeatedScalarFieldContainer[float]
    disable_highpass: bool
    dt: float
    frequency: _containers.RepeatedScalarFieldContainer[float]
    highpass_cutoff: float
    learning_rate: _containers.RepeatedScalarFieldContainer[float]
    lr_decay: float
    max_episodes: int
    normalize_response: bool
    response_clip: float
    response_rms_rate: float
    shift_leak: float
    shift_limit: float
    trust_region: float
    def __init__(self, action_dim: _Optional[int] = ..., dt: _Optional[float] = ..., amplitude: _Optional[_Iterable[float]] = ..., frequency: _Optional[_Iterable[float]] = ..., learning_rate: _Optional[_Iterable[float]] = ..., highpass_cutoff: _Optional[float] = ..., disable_highpass: bool = ..., action_low: _Optional[_Iterable[float]] = ..., action_high: _Optional[_Iterable[float]] = ..., shift_limit: _Optional[float] = ..., lr_decay: _Optional[float] = ..., max_episodes: _Optional[int] = ..., normalize_response: bool = ..., response_rms_rate: _Optional[float] = ..., response_clip: _Optional[float] = ..., shift_leak: _Optional[float] = ..., trust_region: _Optional[float] = ...) -> None: ...

class SessionProgress(_message.Message):
    __slots__ = ["episodes_completed", "response_mean_square"]
    EPISODES_COMPLETED_FIELD_NUMBER: _ClassVar[int]
    RESPONSE_MEAN_SQUARE_FIELD_NUMBER: _ClassVar[int]
    episodes_completed: int
    response_mean_square: float
    def __init__(self, episodes_completed: _Optional[int] = ..., response_mean_square: _Optional[float] = ...) -> None: ...

class StepBatchRequest(_message.Message):
    __slots__ = ["probe", "q_references", "q_values"]
    PROBE_FIELD_NUMBER: _ClassVar[int]
    Q_REFERENCES_FIELD_NUMBER: _ClassVar[int]
    Q_VALUES_FIELD_NUMBER: _ClassVar[int]
    probe: ProbeBatchRequest
    q_references: _containers.RepeatedScalarFieldContainer[float]
    q_values: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, probe: _Optional[_Union[ProbeBatchRequest, _Mapping]] = ..., q_values: _Optional[_Iterable[float]] = ..., q_references: _Optional[_Iterable[float]] = ...) -> None: ...

class StepBatchResponse(_message.Message):
    __slots__ = ["actions", "episodes_completed", "probes", "response_mean_squares", "shifts"]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    EPISODES_COMPLETED_FIELD_NUMBER: _ClassVar[int]
    PROBES_FIELD_NUMBER: _ClassVar[int]
    RESPONSE_MEAN_SQUARES_FIELD_NUMBER: _ClassVar[int]
    SHIFTS_FIELD_NUMBER: _ClassVar[int]
    actions: _containers.RepeatedScalarFieldContainer[float]
    episodes_completed: _containers.RepeatedScalarFieldContainer[int]
    probes: _containers.RepeatedScalarFieldContainer[float]
    response_mean_squares: _containers.RepeatedScalarFieldContainer[float]
    shifts: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, probes: _Optional[_Iterable[float]] = ..., actions: _Optional[_Iterable[float]] = ..., shifts: _Optional[_Iterable[float]] = ..., episodes_completed: _Optional[_Iterable[int]] = ..., response_mean_squares: _Optional[_Iterable[float]] = ...) -> None: ...

class StepLinearBatchRequest(_message.Message):
    __slots__ = ["critic_gains", "critic_offsets", "paired", "probe"]
    CRITIC_GAINS_FIELD_NUMBER: _ClassVar[int]
    CRITIC_OFFSETS_FIELD_NUMBER: _ClassVar[int]
    PAIRED_FIELD_NUMBER: _ClassVar[int]
    PROBE_FIELD_NUMBER: _ClassVar[int]
    critic_gains: _containers.RepeatedScalarFieldContainer[float]
    critic_offsets: _containers.RepeatedScalarFieldContainer[float]
    paired: bool
    probe: ProbeBatchRequest
    def __init__(self, probe: _Optional[_Union[ProbeBatchRequest, _Mapping]] = ..., critic_gains: _Optional[_Iterable[float]] = ..., critic_offsets: _Optional[_Iterable[float]] = ..., paired: bool = ...) -> None: ...

class StepStreamRequest(_message.Message):
    __slots__ = ["probe_batch", "report_batch", "step_batch", "step_linear_batch"]
    PROBE_BATCH_FIELD_NUMBER: _ClassVar[int]
    REPORT_BATCH_FIELD_NUMBER: _ClassVar[int]
    STEP_BATCH_FIELD_NUMBER: _ClassVar[int]
    STEP_LINEAR_BATCH_FIELD_NUMBER: _ClassVar[int]
    probe_batch: ProbeBatchRequest
    report_batch: ReportBatchRequest
    step_batch: StepBatchRequest
    step_linear_batch: StepLinearBatchRequest
    def __init__(self, probe_batch: _Optional[_Union[ProbeBatchRequest, _Mapping]] = ..., report_batch: _Optional[_Union[ReportBatchRequest, _Mapping]] = ..., step_linear_batch: _Optional[_Union[StepLinearBatchRequest, _Mapping]] = ..., step_batch: _Optional[_Union[StepBatchRequest, _Mapping]] = ...) -> None: ...

class StepStreamResponse(_message.Message):
    __slots__ = ["error", "probe_batch", "report_batch", "step_batch", "step_linear_batch"]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    PROBE_BATCH_FIELD_NUMBER: _ClassVar[int]
    REPORT_BATCH_FIELD_NUMBER: _ClassVar[int]
    STEP_BATCH_FIELD_NUMBER: _ClassVar[int]
    STEP_LINEAR_BATCH_FIELD_NUMBER: _ClassVar[int]
    error: StreamError
    probe_batch: ProbeBatchResponse
    report_batch: ReportBatchResponse
    step_batch: StepBatchResponse
    step_linear_batch: StepBatchResponse
    def __init__(self, probe_batch: _Optional[_Union[ProbeBatchResponse, _Mapping]] = ..., report_batch: _Optional[_Union[ReportBatchResponse, _Mapping]] = ..., error: _Optional[_Union[StreamError, _Mapping]] = ..., step_linear_batch: _Optional[_Union[StepBatchResponse, _Mapping]] = ..., step_batch: _Optional[_Union[StepBatchResponse, _Mapping]] = ...) -> None: ...

class StreamError(_message.Message):
    __slots__ = ["code", "item", "message"]
    CODE_FIELD_NUMBER: _ClassVar[int]
    ITEM_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    code: int
    item: BatchItem
    message: str
    def __init__(self, code: _Optional[int] = ..., message: _Optional[str] = ..., item: _Optional[_Union[BatchItem, _Mapping]] = ...) -> None: ...
