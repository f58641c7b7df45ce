"""``TARLoss``: a TorchRL ``LossModule`` that owns the reduction of per-step losses over time.

The inner objective (any ``LossModule`` built with ``reduction="none"``, e.g. torchrl's
``BCLoss``) computes unreduced per-step losses on a ``[B, L]`` TensorDict of segments.
``TARLoss`` reduces any trailing event dimensions (action dims, chunk horizon) to ``[B, L]``,
weights the steps of each segment with a registered weighting (``"tar"`` by default, the
uniform mean, the paper's controls and the baselines from the literature by name) and returns
the segment loss of Eq. 2, averaged over the segments that have at least one valid step. A
stateful weighting (``dro_time``) keeps its state in a buffer of ``TARLoss``, updated on each
training step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.distributed as torch_dist
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.objectives import LossModule

from .elementwise import element_mean, masked_mean
from .schedule import MixSchedule
from .supervision import perturb_target
from .tar import (
    DEFAULT_EPS,
    DEFAULT_GAMMA,
    DEFAULT_W_MAX,
)
from .weighting import (
    DEFAULT_DRO_BINS,
    DEFAULT_DRO_ETA,
    DEFAULT_FOCAL_BETA,
    DEFAULT_GRIPPER_DIMS,
    DEFAULT_KEYFRAME_FACTOR,
    DEFAULT_KEYFRAME_FRACTION,
    DEFAULT_TILT,
    DEFAULT_TRUNCATE_FRACTION,
    WeightingParams,
    get_weighting,
    perturb_mask,
)

__all__ = ["COMPILE_MODES", "NONFINITE_MODES", "TARLoss", "compiles_weights", "segment_mean"]

#: ``nonfinite`` of :class:`TARLoss`: what a NaN/inf per-step loss does (raise, or make ``loss_tar`` non-finite).
NONFINITE_MODES = ("raise", "propagate")
#: ``compile_weights`` of :class:`TARLoss`: ``auto`` (on CUDA, when triton is installed), ``always``, ``never``.
COMPILE_MODES = ("auto", "always", "never")


def _sum_over_ranks(stats: Tensor) -> Tensor:
    """``stats`` summed over the ranks of the process group (the state update's batch statistics)."""
    torch_dist.all_reduce(stats)
    return stats


def compiles_weights(compile_weights: str, device: torch.device) -> bool:
    """Whether ``TARLoss(compile_weights=...)`` compiles its weighting for tensors on ``device``:
    ``always``; ``auto`` for CUDA tensors when inductor can emit triton kernels; never for ``never``
    (and never for the weightings that always run eagerly, see :class:`TARLoss`)."""
    if compile_weights != "auto":
        return compile_weights == "always"
    if device.type != "cuda":
        return False
    from torch.utils._triton import has_triton  # cached

    return has_triton()


def segment_mean(losses: Tensor, weights: Tensor, valid: Tensor) -> Tensor:
    """Eq. 2 per segment, then the mean over segments that have at least one valid step.

    Args:
        losses: ``[..., L]`` per-step losses (padded steps may hold anything, NaN included).
        weights: ``[..., L]`` step weights (unit mean over valid steps for TAR, ones for Eq. 1).
        valid: ``[..., L]`` bool, ``True`` on real steps, ``False`` on padding.

    Returns:
        A scalar: ``mean_i (1 / M_i) sum_t m_t w_t l_t`` over segments ``i`` with ``M_i > 0``;
        ``0`` when no segment has a valid step.
    """
    zero = torch.zeros((), dtype=losses.dtype, device=losses.device)
    per_step = torch.where(valid, weights.to(losses.dtype) * losses, zero)
    n_valid = valid.sum(-1)
    per_segment = per_step.sum(-1) / n_valid.clamp_min(1).to(losses.dtype)
    return per_segment.sum() / (n_valid > 0).sum().clamp_min(1).to(losses.dtype)


class TARLoss(LossModule):
    """Time-Adaptive Reweighting around a per-step imitation loss (paper Sec. II).

    Args:
        inner (LossModule): computes per-step losses without reducing them, e.g.
            ``BCLoss(actor, loss_function="mse", reduction="none")``. Its output must hold one
            ``loss_*`` entry of shape ``[B, L, ...]`` (the input's batch shape, then any event
            dims); other ``loss_*`` entries must be scalars and are added unweighted.
        weighting (str): a name from :data:`tar_rl.objectives.WEIGHTINGS`: ``"tar"`` (default),
            ``"uniform"`` (Eq. 1), a control: ``"shuffle"``, ``"random"``, ``"invert"``,
            ``"perturb_high"``, ``"perturb_low"``, a baseline from the literature
            (:mod:`~tar_rl.objectives.baselines`): ``"tilted"``, ``"truncate"``, ``"keyframe"``,
            ``"focal"``, ``"dro_time"``, or an element weighting (:mod:`~tar_rl.objectives.elementwise`):
            ``"tar_arm"``, ``"tar_dimnorm"``. An element weighting scores the per-element
            losses before the event dims are averaged; it needs an inner loss with event dims
            whose last axis holds the action dims.

    Keyword Args:
        gamma, w_max, eps, cap: TAR's hyper-parameters, see :func:`tar_rl.tar_weights`
            (``focal`` also caps at ``w_max``, exactly; it needs ``w_max >= 1``).
        tilt: ``t`` of ``tilted`` (:func:`~tar_rl.objectives.tilted_weights`), ``> 0``; default ``1.0``.
        truncate_fraction: ``q`` of ``truncate``, in ``[0, 1)``; default ``0.1``.
        keyframe_fraction, keyframe_factor: ``f`` in ``(0, 1)`` (default ``0.3``) and ``K >= 1``
            (default ``5.0``) of ``keyframe``.
        focal_beta: ``beta`` of ``focal``, ``>= 0``; default ``1.0``.
        dro_eta, dro_bins: the step size ``eta > 0`` (default ``0.01``) and the number of bins of
            normalised episode time ``G >= 1`` (default ``10``) of ``dro_time``
            (:func:`~tar_rl.objectives.dro_time_weights`).
        gripper_dims: the action dims ``tar_arm`` averages uniformly; default ``(-1,)``.
        schedule (MixSchedule): when TAR (and every other weighting) is mixed in; default: fully
            on from the first step. Before ``schedule.start`` every weighting is the uniform mean.
        loss_key (NestedKey): the inner output holding the per-step loss; default: its only
            ``loss_*`` entry.
        perturb_fraction (float): for ``perturb_*``, the fraction of each segment's valid steps
            whose expert action is corrupted at full schedule strength (scaled by alpha).
            Not given by the paper; default ``0.25``.
        perturb_scale (float): for ``perturb_*``, the std of the Gaussian noise added to those
            actions, in action units. Not given by the paper; default ``0.1``.
        seed (int): seeds the generator of the stochastic controls; its state is part of
            ``state_dict()`` so that a resumed run draws the same numbers.
        return_weights (bool): also return the ``[B, L]`` weights under ``"weights"``.
        auto_step (bool): advance the schedule by one on every forward pass made in training
            mode with gradients enabled (default). Set ``False`` with gradient accumulation and
            call :meth:`advance` once per optimiser step instead.
        compile_weights (str): run the weighting (``tar``, ``invert``, the baselines) through
            ``torch.compile``: ``"auto"`` (default) on CUDA when triton is available, ``"always"``, ``"never"``.
            On a GPU the weighting of a ``[B, L]`` batch is some thirty tiny kernels, whose
            launches cost about 0.5 ms a step; compiled, they fuse into a few. The compiled
            weights equal the eager ones up to float rounding. Uniform, the stochastic
            controls and the weightings that read time or keep a state (``dro_time``) always run
            eagerly (nothing to fuse; random generators; checks of the time input and a state update).
        nonfinite (str): what a NaN or infinite per-step loss at a valid step does: ``"raise"``
            (default) a ``ValueError`` from the weighting; ``"propagate"`` makes ``loss_tar``
            non-finite (the weights are computed as if that loss were 0; it still enters Eq. 2),
            so that a training loop's own non-finite handling sees it after ``backward``, on
            every rank of a distributed job.

    Input: a TensorDict of batch shape ``[B, L]`` (segments x steps), holding what the inner
    loss reads and the validity mask at ``tensor_keys.valid`` (``True`` on real steps,
    ``False`` on padding; default ``("collector", "mask")``, which
    ``SliceSampler(pad_output=True)`` writes; if absent, every step is valid). A weighting that
    reads time (``dro_time``) also needs each step's index in its episode at ``tensor_keys.step``
    and the episode's length at ``tensor_keys.episode_length`` (integer ``[B, L]``; the dataset's
    ``step`` and the ``episode_length`` that :class:`~tar_rl.data.SegmentSampler` writes); they are
    then part of :attr:`in_keys` and :attr:`time_keys`.

    State: ``schedule_step`` and, for a stateful weighting, ``weighting_state`` (``dro_time``: the
    ``[G]`` log group weights, float64, uniform at first) are buffers, and the generator of the
    stochastic controls is extra state: all are in ``state_dict()``, so a resumed run continues
    them exactly. ``weighting_state`` moves only on a training step (training mode with gradients
    enabled, as the schedule does); an evaluation-mode or ``no_grad`` call computes the weights
    from the state this batch would give but leaves the state as it was. In a distributed job
    (``torch.distributed`` initialised) the batch statistics of the update (``dro_time``: per-bin
    loss sums and valid counts) are summed over the ranks on a training step, so that every rank
    holds the same state: every rank must then call the loss on every training step, as DDP's
    backward already requires.

    Output keys: ``loss_tar`` (the only differentiable entry) and the detached diagnostics
    ``tar_mix`` (alpha), ``weight_max``, ``weight_ess`` (mean over segments of the effective
    sample size ``(sum w)^2 / (M sum w^2)``, 1 for uniform weights), ``uniform_loss`` (Eq. 1
    on the same losses), ``schedule_step``; ``perturbed_fraction`` for the perturbation
    controls; ``aux_<key>`` for extra scalar inner losses; ``weights`` if asked.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.objectives import BCLoss
        >>> actor = TensorDictModule(torch.nn.Linear(3, 2), ["observation"], ["action"])
        >>> loss = TARLoss(BCLoss(actor, loss_function="mse", reduction="none"))
        >>> data = TensorDict(
        ...     {"observation": torch.randn(4, 8, 3), "action": torch.randn(4, 8, 2),
        ...      ("collector", "mask"): torch.ones(4, 8, dtype=torch.bool)}, [4, 8])
        >>> out = loss(data)
        >>> out["loss_tar"].shape, sorted(k for k in out.keys() if k.startswith("loss"))
        (torch.Size([]), ['loss_tar'])
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable input keys.

        Attributes:
            valid (NestedKey): bool ``[B, L]`` (or ``[B, L, 1]``) mask, ``True`` on real steps.
                Defaults to ``("collector", "mask")``.
            action (NestedKey): the supervision target that the ``perturb_*`` controls corrupt
                (:mod:`~tar_rl.objectives.supervision`). Defaults to the inner loss's declared
                ``target_key``, else its ``action`` key (torchrl's BC losses), else ``"action"``.
            event_valid (NestedKey, optional): bool ``[B, L, ...]`` mask over the event dims of
                the per-step loss, ``True`` on real elements (e.g. the valid part of an action
                chunk near the end of a trajectory). The per-step loss is the mean over the
                valid elements. Defaults to ``None``: a plain mean over the event dims.
            step (NestedKey): integer ``[B, L]``, each step's index in its episode; read by the
                weightings that read time (``dro_time``). Defaults to ``"step"``.
            episode_length (NestedKey): integer ``[B, L]``, the length of each step's episode;
                read with ``step``. Defaults to ``"episode_length"``.
        """

        valid: NestedKey = ("collector", "mask")
        action: NestedKey = "action"
        event_valid: NestedKey | None = None
        step: NestedKey = "step"
        episode_length: NestedKey = "episode_length"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = ["loss_tar", "tar_mix", "weight_max", "weight_ess", "uniform_loss", "schedule_step"]

    inner: LossModule

    def __init__(
        self,
        inner: LossModule,
        weighting: str = "tar",
        *,
        gamma: float = DEFAULT_GAMMA,
        w_max: float = DEFAULT_W_MAX,
        eps: float = DEFAULT_EPS,
        cap: str = "paper",
        tilt: float = DEFAULT_TILT,
        truncate_fraction: float = DEFAULT_TRUNCATE_FRACTION,
        keyframe_fraction: float = DEFAULT_KEYFRAME_FRACTION,
        keyframe_factor: float = DEFAULT_KEYFRAME_FACTOR,
        focal_beta: float = DEFAULT_FOCAL_BETA,
        dro_eta: float = DEFAULT_DRO_ETA,
        dro_bins: int = DEFAULT_DRO_BINS,
        gripper_dims: tuple[int, ...] = DEFAULT_GRIPPER_DIMS,
        schedule: MixSchedule | None = None,
        loss_key: NestedKey | None = None,
        perturb_fraction: float = 0.25,
        perturb_scale: float = 0.1,
        seed: int = 0,
        return_weights: bool = False,
        auto_step: bool = True,
        compile_weights: str = "auto",
        nonfinite: str = "raise",
    ) -> None:
        if not isinstance(inner, LossModule):
            raise TypeError(f"inner must be a torchrl LossModule, got {type(inner).__name__}.")
        reduction = getattr(inner, "reduction", "none")
        if reduction != "none":
            raise ValueError(
                f"TARLoss needs unreduced per-step losses, but the inner {type(inner).__name__} has "
                f"reduction={reduction!r}: build it with reduction='none'."
            )
        if not 0 <= perturb_fraction <= 1:
            raise ValueError(f"perturb_fraction must lie in [0, 1], got {perturb_fraction!r}.")
        if not (math.isfinite(perturb_scale) and perturb_scale >= 0):
            raise ValueError(f"perturb_scale must be a finite number >= 0, got {perturb_scale!r}.")
        if compile_weights not in COMPILE_MODES:
            raise ValueError(f"compile_weights must be one of {list(COMPILE_MODES)}, got {compile_weights!r}.")
        if nonfinite not in NONFINITE_MODES:
            raise ValueError(f"nonfinite must be one of {list(NONFINITE_MODES)}, got {nonfinite!r}.")
        schedule = MixSchedule() if schedule is None else schedule
        if not isinstance(schedule, MixSchedule):
            raise TypeError(f"schedule must be a MixSchedule, got {type(schedule).__name__}.")
        super().__init__()
        self.inner = inner
        self.weighting = get_weighting(weighting)
        self.weighting_params = WeightingParams(
            gamma=gamma,
            w_max=w_max,
            eps=eps,
            cap=cap,
            tilt=tilt,
            truncate_fraction=truncate_fraction,
            keyframe_fraction=keyframe_fraction,
            keyframe_factor=keyframe_factor,
            focal_beta=focal_beta,
            dro_eta=dro_eta,
            dro_bins=dro_bins,
            gripper_dims=gripper_dims,
        )
        if self.weighting.check is not None:
            self.weighting.check(self.weighting_params)
        self.schedule = schedule
        self.loss_key = loss_key
        self.perturb_fraction = float(perturb_fraction)
        self.perturb_scale = float(perturb_scale)
        self.return_weights = return_weights
        self.auto_step = auto_step
        self.compile_weights = compile_weights
        self.nonfinite = nonfinite
        self.register_buffer("schedule_step", torch.zeros((), dtype=torch.long))
        if self.weighting.initial_state is not None:
            self.register_buffer("weighting_state", self.weighting.initial_state(self.weighting_params))
        self._generator = torch.Generator().manual_seed(seed)
        self._compiled_weights = None  # the weighting through torch.compile, built at its first use
        target = getattr(inner, "target_key", None)
        if target is None:
            target = getattr(getattr(inner, "tensor_keys", None), "action", None)
        if target is not None:
            self.set_keys(action=target)
        extra_out = (["perturbed_fraction"] if self.weighting.perturb else []) + (["weights"] if return_weights else [])
        self.out_keys = [*self.out_keys, *extra_out]

    # -- TorchRL plumbing -------------------------------------------------------------------

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = [*self.inner.in_keys, self.tensor_keys.valid, *self.time_keys]
        if self.tensor_keys.event_valid is not None:
            keys.append(self.tensor_keys.event_valid)
        return list(dict.fromkeys(keys))

    @property
    def time_keys(self) -> tuple[NestedKey, ...]:
        """The keys of each step's position in its episode (``step``, ``episode_length``) when the
        weighting reads time; empty otherwise."""
        if not self.weighting.reads_time:
            return ()
        return (self.tensor_keys.step, self.tensor_keys.episode_length)

    def __getstate__(self) -> dict:
        state = super().__getstate__()
        state["_compiled_weights"] = None  # a compiled function does not pickle: a copy compiles its own
        return state

    def get_extra_state(self) -> dict:
        return {"generator": self._generator.get_state()}

    def set_extra_state(self, state: dict) -> None:
        self._generator.set_state(state["generator"])

    def advance(self, steps: int = 1) -> None:
        """Move the schedule on by ``steps`` optimiser steps (for ``auto_step=False``)."""
        self.schedule_step.add_(steps)

    # -- The objective ----------------------------------------------------------------------

    def step_losses(self, tensordict: TensorDictBase) -> Tensor:
        """The inner loss's per-step losses ``[B, L]`` (event dims reduced), unweighted.

        For inspection (e.g. recording losses along whole demonstrations): it neither weights
        the steps nor advances the schedule.
        """
        out = self.inner(tensordict)
        return self._step_losses(out, self._loss_entry(out), tensordict)

    def step_and_dim_losses(self, tensordict: TensorDictBase) -> tuple[Tensor, Tensor | None]:
        """The per-step losses of :meth:`step_losses` and, from the same pass of the inner loss, each
        action dim's share of them.

        Returns:
            ``(steps, dims)``: ``steps`` as :meth:`step_losses` (``[B, L]``, the batch shape); ``dims``
            ``[B, L, A]`` (the batch shape, then the loss's last axis, the action dims): each action
            dim's loss per step, the mean over the other event dims (e.g. a chunk's horizon) over the
            valid entries only (``event_valid``; 0 where a step has none). ``dims`` is ``None`` when
            the inner loss has no event dims (one loss per step, nothing per action dim).

        When every action dim has the same valid entries (always without ``event_valid``; a chunk's
        mask covers whole actions), a step's loss is the mean of its ``A`` dim losses. For inspection,
        like :meth:`step_losses`: it neither weights the steps nor advances the schedule.
        """
        out = self.inner(tensordict)
        key = self._loss_entry(out)
        return self._step_losses(out, key, tensordict), self._dim_losses(out, key, tensordict)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Weighted segment loss of Eq. 2 on a ``[B, L]`` TensorDict; does not modify it."""
        if tensordict.batch_dims < 2:
            raise ValueError(
                f"TARLoss expects a TensorDict of segments with batch shape [B, L], got "
                f"{list(tensordict.batch_size)}: reshape the sampler's flat output, e.g. "
                "`batch.reshape(-1, slice_len)`."
            )
        valid = self._read_valid(tensordict)
        mix = self.schedule(self.schedule_step)
        spec = self.weighting
        generator = self._generator if spec.stochastic else None
        diagnostics: dict[str, Tensor] = {}

        if spec.perturb is not None:
            with torch.no_grad():
                clean_out = self.inner(tensordict)
                clean = self._scored(self._step_losses(clean_out, self._loss_entry(clean_out), tensordict), valid)
            chosen = perturb_mask(
                clean, valid, fraction=self.perturb_fraction * mix, which=spec.perturb, generator=generator
            )
            tensordict = perturb_target(tensordict, self.tensor_keys.action, chosen, self.perturb_scale, generator)
            diagnostics["perturbed_fraction"] = chosen.sum() / valid.sum().clamp_min(1)

        training_step = self.training and torch.is_grad_enabled()
        inputs = self._time_inputs(tensordict) if spec.reads_time else {}
        if spec.initial_state is not None:
            inputs["state"] = self.weighting_state
            distributed = training_step and torch_dist.is_available() and torch_dist.is_initialized()
            inputs["reduce"] = _sum_over_ranks if distributed else None

        out = self.inner(tensordict)
        key = self._loss_entry(out)
        # The weights are stop-gradient (Eq. 3): the weighting sees detached losses.
        if spec.elementwise:
            elements, event_valid = self._element_losses(out, key, tensordict)
            weigh = self._weight_function(elements.device)
            element_valid = event_valid & valid.reshape(valid.shape + (1,) * (elements.ndim - valid.ndim))
            scored = self._scored(elements.detach(), element_valid)
            element_weights = weigh(scored, element_valid, self.weighting_params, mix, generator, **inputs)
            losses = element_mean(elements, event_valid)
            weights = element_mean(element_weights, event_valid)  # a step's weight: its elements' mean
            loss = segment_mean(element_mean(element_weights * elements, event_valid), torch.ones_like(weights), valid)
        else:
            losses = self._step_losses(out, key, tensordict)
            scored = self._scored(losses.detach(), valid)
            weigh = self._weight_function(losses.device)
            weights = weigh(scored, valid, self.weighting_params, mix, generator, **inputs)
            if spec.initial_state is not None:
                weights, state = weights
                if training_step:
                    self.weighting_state.copy_(state)
            loss = segment_mean(losses, weights, valid)
        for name, value in self._extra_losses(out, key).items():
            loss = loss + value
            diagnostics[f"aux_{name}"] = value.detach()

        with torch.no_grad():
            m = valid.to(weights.dtype)
            n_valid = m.sum(-1)
            square_sum = (weights.square() * m).sum(-1)
            ess = (weights * m).sum(-1).square() / (n_valid * square_sum).clamp_min(torch.finfo(weights.dtype).tiny)
            nonempty = n_valid > 0
            result = {
                "loss_tar": loss,
                "tar_mix": torch.as_tensor(mix, dtype=torch.float32),
                "weight_max": weights.detach().max(),
                "weight_ess": (ess * nonempty).sum() / nonempty.sum().clamp_min(1),
                "uniform_loss": segment_mean(losses.detach(), m, valid),
                "schedule_step": self.schedule_step.clone(),
                **diagnostics,
            }
            if self.return_weights:
                result["weights"] = weights.detach()

        if self.auto_step and training_step:
            self.schedule_step.add_(1)
        return TensorDict(result, batch_size=[])

    # -- Helpers ----------------------------------------------------------------------------

    def _scored(self, losses: Tensor, valid: Tensor) -> Tensor:
        """The detached losses the weighting scores: with ``nonfinite="propagate"``, a non-finite one is 0.

        Finite losses pass unchanged (the same values, so the same weights), without a host sync.
        """
        if self.nonfinite == "raise":
            return losses
        return losses.masked_fill(valid & ~torch.isfinite(losses), 0.0)

    def _weight_function(self, device: torch.device):
        """The weighting's function, compiled where ``compile_weights`` says so."""
        spec = self.weighting
        eager = spec.stochastic or spec.perturb is not None or spec.name == "uniform"
        eager = eager or spec.reads_time or spec.initial_state is not None
        if eager or not compiles_weights(self.compile_weights, device):
            return spec.weights
        if self._compiled_weights is None:
            self._compiled_weights = torch.compile(spec.weights, dynamic=False)
        return self._compiled_weights

    def _time_inputs(self, tensordict: TensorDictBase) -> dict[str, Tensor]:
        """``step`` and ``episode_length``, ``[B, L]`` integer tensors, for a weighting that reads time."""
        batch = tensordict.batch_size
        inputs = {}
        for name, key in (("step", self.tensor_keys.step), ("episode_length", self.tensor_keys.episode_length)):
            value = tensordict.get(key, None)
            if value is None:
                raise KeyError(
                    f"the {self.weighting.name} weighting reads each step's position in its episode, but the batch "
                    f"has no {key!r} entry (the {name} of every step): sample it with the segments "
                    f"(SegmentSampler writes 'episode_length'; the dataset stores 'step'), or say where it is "
                    f"with TARLoss.set_keys({name}=...)."
                )
            while value.ndim > len(batch) and value.shape[-1] == 1:
                value = value.squeeze(-1)
            if value.shape != batch or value.is_floating_point() or value.dtype == torch.bool:
                raise ValueError(
                    f"the {name} entry {key!r} must be an integer tensor of the batch shape {list(batch)}, "
                    f"got {value.dtype} {list(value.shape)}."
                )
            inputs[name] = value
        return inputs

    def _read_valid(self, tensordict: TensorDictBase) -> Tensor:
        batch = tensordict.batch_size
        key = self.tensor_keys.valid
        valid = tensordict.get(key, None)
        if valid is None:
            return torch.ones(batch, dtype=torch.bool, device=tensordict.device)
        if valid.dtype != torch.bool:
            raise TypeError(f"the validity mask {key!r} must be torch.bool (True on real steps), got {valid.dtype}.")
        while valid.ndim > len(batch) and valid.shape[-1] == 1:
            valid = valid.squeeze(-1)
        if valid.shape != batch:
            raise ValueError(
                f"the validity mask {key!r} has shape {list(valid.shape)}, expected the batch shape {list(batch)}."
            )
        return valid

    def _loss_entry(self, out: TensorDictBase) -> NestedKey:
        if self.loss_key is not None:
            if self.loss_key not in out.keys(True):
                raise KeyError(f"the inner loss returned no {self.loss_key!r}; it returned {list(out.keys())}.")
            return self.loss_key
        names = [k for k in out.keys() if isinstance(k, str) and k.startswith("loss")]
        if len(names) != 1:
            raise ValueError(
                f"the inner loss returned {len(names)} loss entries {names}: say which one holds the "
                "per-step loss with TARLoss(..., loss_key=...)."
            )
        return names[0]

    def _extra_losses(self, out: TensorDictBase, main: NestedKey) -> dict[str, Tensor]:
        extra = {}
        for key in out.keys():
            if isinstance(key, str) and key.startswith("loss") and key != main:
                value = out.get(key)
                if value.ndim != 0:
                    raise ValueError(
                        f"the inner loss's extra entry {key!r} has shape {list(value.shape)}: extra "
                        "losses are added unweighted and must be scalars."
                    )
                extra[key] = value
        return extra

    def _step_losses(self, out: TensorDictBase, key: NestedKey, tensordict: TensorDictBase) -> Tensor:
        """The inner per-step loss at ``key`` as ``[B, L]``: trailing event dims averaged away."""
        loss = self._checked_loss(out, key, tensordict)
        if loss.ndim == tensordict.batch_dims:
            return loss
        if self.tensor_keys.event_valid is None:
            return loss.mean(tuple(range(tensordict.batch_dims, loss.ndim)))
        return element_mean(loss, self._event_valid(loss, tensordict), tensordict.batch_dims)

    def _dim_losses(self, out: TensorDictBase, key: NestedKey, tensordict: TensorDictBase) -> Tensor | None:
        """The inner loss at ``key`` per step and action dim ``[*batch, A]`` (see :meth:`step_and_dim_losses`)."""
        loss = self._checked_loss(out, key, tensordict)
        if loss.ndim == tensordict.batch_dims:
            return None
        axes = tuple(range(tensordict.batch_dims, loss.ndim - 1))  # the event dims but the action dims
        if self.tensor_keys.event_valid is None:
            return loss.mean(axes) if axes else loss
        return masked_mean(loss, self._event_valid(loss, tensordict), axes)  # padding may be NaN

    def _element_losses(self, out: TensorDictBase, key: NestedKey, tensordict: TensorDictBase) -> tuple[Tensor, Tensor]:
        """The inner per-element loss ``[B, L, *event, A]`` and its event mask (all ``True`` if no ``event_valid``)."""
        loss = self._checked_loss(out, key, tensordict)
        if tensordict.batch_dims != 2:
            raise ValueError(
                f"objective {self.weighting.name!r} weights per-element losses of a [B, L] batch, got batch shape "
                f"{list(tensordict.batch_size)}: reshape it to [B, L]."
            )
        if loss.ndim == tensordict.batch_dims:
            raise ValueError(
                f"objective {self.weighting.name!r} weights per-element losses, but the inner loss's {key!r} has one "
                f"loss per step (shape {list(loss.shape)}): it needs event dims with the action dims last."
            )
        if self.tensor_keys.event_valid is None:
            return loss, torch.ones(loss.shape, dtype=torch.bool, device=loss.device)
        return loss, self._event_valid(loss, tensordict)

    def _checked_loss(self, out: TensorDictBase, key: NestedKey, tensordict: TensorDictBase) -> Tensor:
        loss = out.get(key)
        batch = tensordict.batch_size
        if loss.shape[: len(batch)] != batch:
            raise ValueError(
                f"the inner loss's {key!r} has shape {list(loss.shape)}, but TARLoss needs per-step "
                f"losses shaped like the batch {list(batch)} (then any event dims): build the inner "
                "loss with reduction='none' and do not pass it a pad_mask (which flattens the output)."
            )
        return loss

    def _event_valid(self, loss: Tensor, tensordict: TensorDictBase) -> Tensor:
        """The ``event_valid`` mask broadcast to the loss's shape."""
        event_key = self.tensor_keys.event_valid
        event_valid = tensordict.get(event_key)
        if event_valid.dtype != torch.bool or event_valid.shape != loss.shape[: event_valid.ndim]:
            raise ValueError(
                f"the event mask {event_key!r} must be torch.bool with a leading part of the loss's "
                f"shape {list(loss.shape)}, got {event_valid.dtype} {list(event_valid.shape)}."
            )
        event_valid = event_valid.reshape(event_valid.shape + (1,) * (loss.ndim - event_valid.ndim))
        return event_valid.expand_as(loss)
