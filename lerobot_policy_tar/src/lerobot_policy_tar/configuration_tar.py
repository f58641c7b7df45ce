"""The policy configs: each base policy's own config plus TAR's settings in ``policy.tar``.

``--policy.type=act_tar`` (or ``diffusion_tar``, ``smolvla_tar``, ``pi0_tar``, ``pi05_tar``) trains the LeRobot
policy of that name with TAR over time instead of the uniform mean; every field of the base policy keeps its name
and default, and TAR's settings are ``--policy.tar.gamma=...`` and so on (:class:`TARSettings`). LeRobot finds the
policy class and the processors of a config by the naming convention of its modules (``configuration_tar`` ->
``modeling_tar``, ``processor_tar``; ``ACTTARConfig`` -> ``ACTTARPolicy``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.policies.pi0.configuration_pi0 import PI0Config
from lerobot.policies.pi05.configuration_pi05 import PI05Config
from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig

from .tar_source import DEFAULT_EPS, DEFAULT_GAMMA, DEFAULT_W_MAX, MixSchedule, check_tar_params

__all__ = [
    "BASES",
    "PI0_FAST_REFUSAL",
    "SAMPLED_SIGNALS",
    "TIME_AXES",
    "ACTTARConfig",
    "DiffusionTARConfig",
    "PI0TARConfig",
    "PI05TARConfig",
    "SmolVLATARConfig",
    "TARSettings",
    "tar_config_class",
]

#: ``segment``: the paper's time axis, ``slice_len`` consecutive observation steps, each with its own chunk.
#: ``chunk``: the entries of one action chunk (one observation step), a cheaper reinterpretation.
TIME_AXES: tuple[str, ...] = ("segment", "chunk")

#: The ranking signals of a policy whose loss is one draw of a time (noise level) and a noise: besides the loss,
#: ``action_error`` (the error of the action chunk its prediction implies) and ``time_normalized`` (the loss over a
#: running mean of the loss at its time). ACT's loss is not sampled: it offers ``loss`` alone.
SAMPLED_SIGNALS: tuple[str, ...] = ("loss", "action_error", "time_normalized")

PI0_FAST_REFUSAL = (
    "pi0_fast is not supported by TAR: its loss is a cross-entropy over FAST tokens, which encode a whole action "
    "chunk at once, so there is no per-step loss to weight; use pi0_tar or pi05_tar."
)


@dataclass
class TARSettings:
    """TAR's settings (``--policy.tar.<name>``): the names and defaults of tar-rl's objective.

    Attributes:
        gamma: softmax temperature on the within-segment z-scores (paper Eq. 6), ``> 0``.
        w_max: cap on a step's weight in units of the mean weight (Eq. 8), ``> 0``; ``inf`` for no cap.
        eps: added to the segment's standard deviation (Eq. 5), ``> 0``.
        cap: ``paper`` (clip once, renormalise: Eq. 8 as printed) or ``exact`` (the cap holds exactly; ``w_max >= 1``).
        start: training steps with the uniform mean before TAR starts (the paper: 20_000 of 100_000).
        ramp: training steps over which TAR's mixing weight rises from 0 to 1 (the paper: 30_000); 0 switches at once.
        shape: ``linear`` or ``cosine`` ramp.
        time_axis: ``segment`` (the paper: weights over ``slice_len`` consecutive observation steps) or ``chunk``
            (weights over the entries of one action chunk).
        slice_len: the segment length ``L`` of ``segment`` mode (each item of a batch holds ``L`` observation steps,
            so the base model sees ``L`` times the batch); at most the dataset's longest episode.
        signal: what the weights rank the steps by (tar-rl's ``objective.signal``): ``loss``, the per-step loss
            itself; for a policy whose loss is one random draw of a time and a noise (diffusion, SmolVLA, pi0,
            pi0.5) also ``action_error`` or ``time_normalized`` (docs/lerobot.md). The loss the weights multiply
            is the policy's own in every case.
    """

    gamma: float = DEFAULT_GAMMA
    w_max: float = DEFAULT_W_MAX
    eps: float = DEFAULT_EPS
    cap: str = "paper"
    start: int = 0
    ramp: int = 0
    shape: str = "linear"
    time_axis: str = "segment"
    slice_len: int = 16
    signal: str = "loss"

    def validate(self) -> None:
        """Raise a ``ValueError`` naming the first setting out of range.

        Called when the dataset's delta indices are read and when the policy is built, both before training: the
        command-line parser turns an exception raised while it builds a config into a message without the reason.
        """
        try:
            check_tar_params(gamma=self.gamma, w_max=self.w_max, eps=self.eps, cap=self.cap)
            MixSchedule(start=self.start, ramp=self.ramp, shape=self.shape)
        except ValueError as error:
            raise ValueError(f"policy.tar: {error}") from None
        if self.time_axis not in TIME_AXES:
            raise ValueError(f"policy.tar.time_axis must be one of {TIME_AXES}, got {self.time_axis!r}.")
        if isinstance(self.slice_len, bool) or not isinstance(self.slice_len, int) or self.slice_len < 1:
            raise ValueError(f"policy.tar.slice_len must be an int >= 1, got {self.slice_len!r}.")

    @property
    def schedule(self) -> MixSchedule:
        return MixSchedule(start=self.start, ramp=self.ramp, shape=self.shape)


@dataclass
class TARConfigMixin:
    """TAR's settings and the time axis, shared by the five configs (first base of each).

    In ``segment`` mode an item of the dataset holds the base policy's observation and action windows for ``L``
    consecutive steps: the delta indices are the base policy's, extended by ``L - 1`` steps.
    """

    tar: TARSettings = field(default_factory=TARSettings)

    #: The values of ``tar.signal`` this policy offers (``loss`` first).
    tar_signals = ("loss",)

    def check_tar(self) -> None:
        """Raise a ``ValueError`` naming a TAR setting this policy cannot train with."""
        self.tar.validate()
        if self.tar.signal not in self.tar_signals:
            raise ValueError(
                f"policy.tar.signal={self.tar.signal!r} is not offered by {self.type}: it offers "
                f"{list(self.tar_signals)}."
            )

    def validate_features(self) -> None:
        self.check_tar()
        super().validate_features()

    def _segment_extra(self) -> int:
        self.check_tar()
        return self.tar.slice_len - 1 if self.tar.time_axis == "segment" else 0

    @property
    def base_observation_delta_indices(self) -> list | None:
        return super().observation_delta_indices

    @property
    def base_action_delta_indices(self) -> list:
        return super().action_delta_indices

    @property
    def observation_delta_indices(self) -> list | None:
        extra, base = self._segment_extra(), self.base_observation_delta_indices
        if self.tar.time_axis != "segment":
            return base
        first, last = (0, 0) if base is None else (min(base), max(base))
        return list(range(first, last + extra + 1))

    @property
    def action_delta_indices(self) -> list:
        extra, base = self._segment_extra(), self.base_action_delta_indices
        return list(range(min(base), max(base) + extra + 1))


def check_time_quantile(config) -> None:
    """Refuse ``time_normalized`` for pi0 or pi0.5 drawing their flow time from a Beta(alpha, beta) with
    ``beta != 1``: the signal bins a time by its quantile, ``u ** alpha`` for ``Beta(alpha, 1)``."""
    beta = config.time_sampling_beta_beta
    if config.tar.signal == "time_normalized" and beta != 1:
        raise ValueError(
            f"policy.tar.signal='time_normalized' bins {config.type}'s flow times by their quantile under "
            f"Beta(alpha, 1): it needs policy.time_sampling_beta_beta=1 (the default), got {beta!r}."
        )


@PreTrainedConfig.register_subclass("act_tar")
@dataclass
class ACTTARConfig(TARConfigMixin, ACTConfig):
    """LeRobot's ACT trained with TAR (``--policy.type=act_tar``)."""


@PreTrainedConfig.register_subclass("diffusion_tar")
@dataclass
class DiffusionTARConfig(TARConfigMixin, DiffusionConfig):
    """LeRobot's Diffusion Policy trained with TAR (``--policy.type=diffusion_tar``); padding is always masked."""

    tar_signals = SAMPLED_SIGNALS


@PreTrainedConfig.register_subclass("smolvla_tar")
@dataclass
class SmolVLATARConfig(TARConfigMixin, SmolVLAConfig):
    """LeRobot's SmolVLA trained with TAR (``--policy.type=smolvla_tar``)."""

    tar_signals = SAMPLED_SIGNALS


@PreTrainedConfig.register_subclass("pi0_tar")
@dataclass
class PI0TARConfig(TARConfigMixin, PI0Config):
    """LeRobot's pi0 trained with TAR (``--policy.type=pi0_tar``); padded chunk entries are masked."""

    tar_signals = SAMPLED_SIGNALS

    def check_tar(self) -> None:
        super().check_tar()
        check_time_quantile(self)


@PreTrainedConfig.register_subclass("pi05_tar")
@dataclass
class PI05TARConfig(TARConfigMixin, PI05Config):
    """LeRobot's pi0.5 trained with TAR (``--policy.type=pi05_tar``; ``time_axis=chunk`` only, its default: pi0.5's
    preprocessor writes the state of one observation step into the prompt)."""

    tar: TARSettings = field(default_factory=lambda: TARSettings(time_axis="chunk"))
    tar_signals = SAMPLED_SIGNALS

    def check_tar(self) -> None:
        super().check_tar()
        check_time_quantile(self)
        if self.tar.time_axis == "segment" and self.tar.slice_len > 1:
            raise ValueError(
                "pi05_tar supports policy.tar.time_axis=chunk only: pi0.5's preprocessor writes one observation "
                "step's state into the prompt, so a segment of several steps cannot be tokenized; "
                "set --policy.tar.time_axis=chunk."
            )


@PreTrainedConfig.register_subclass("pi0_fast_tar")
@dataclass
class PI0FastTARConfig(PI0Config):
    """Refused: ``--policy.type=pi0_fast_tar`` stops with the reason when the dataset or the policy is made."""

    def validate_features(self) -> None:
        raise ValueError(PI0_FAST_REFUSAL)

    @property
    def observation_delta_indices(self) -> None:
        raise ValueError(PI0_FAST_REFUSAL)

    @property
    def action_delta_indices(self) -> list:
        raise ValueError(PI0_FAST_REFUSAL)


#: base policy -> its TAR config class (the registered type is ``<base>_tar``).
BASES: dict[str, type[PreTrainedConfig]] = {
    "act": ACTTARConfig,
    "diffusion": DiffusionTARConfig,
    "smolvla": SmolVLATARConfig,
    "pi0": PI0TARConfig,
    "pi05": PI05TARConfig,
}


def tar_config_class(base: str) -> type[PreTrainedConfig]:
    """The TAR config class of LeRobot policy ``base`` (``"act"``, ...); a clear error for any other name."""
    if base in ("pi0_fast", "pi0fast"):
        raise ValueError(PI0_FAST_REFUSAL)
    if base not in BASES:
        raise ValueError(f"unknown base policy {base!r} for TAR; supported: {sorted(BASES)}.")
    return BASES[base]
