"""A LeRobot policy as a process that answers action chunks: ``lerobot-tar serve CHECKPOINT``.

tar-rl's MetaWorld evaluator runs in tar-rl's environment (torch 2.13, TorchRL, MetaWorld), which cannot import
LeRobot (torch below 2.12); LeRobot's own MetaWorld environment gives images only. This server bridges the two: it
loads a trained checkpoint of any policy type (``act``, ``act_tar``, ``diffusion``, ...: LeRobot's
``pretrained_model`` folder or the checkpoint folder above it) with its own pre- and post-processors from that
folder, so the policy normalises and unnormalises as it was trained to, and answers requests on stdin with
chunks on stdout. tar-rl's side is ``benchmarks/lerobot_pilot.py``.

The protocol (binary, on stdin and stdout): a *frame* is an 8-byte little-endian length followed by that many bytes
of one array in NumPy's ``.npy`` format, read with ``allow_pickle=False`` (no pickled object is ever loaded).

* Once loaded, the server writes one frame, int64 ``[D, H, A]``: the observation size it expects (the sizes of
  ``observation.state`` and ``observation.environment_state`` together), the chunk length and the action size.
* A request is two frames: observations float32 ``[N, D]`` (tar-rl's observation, split as the exporter
  :mod:`.export` splits it: the first values, as many as the checkpoint's ``observation.state`` has, are
  ``observation.state``, the rest ``observation.environment_state``) and the tasks' texts, a unicode array ``[N]``
  (the ``task`` of each frame: the task's instruction, as the exporter writes it).
* The reply is one frame, float32 ``[N, H, A]``: the policy's ``predict_action_chunk`` on the preprocessed
  observations, passed through the postprocessor (unnormalised, on the CPU).

At EOF on stdin (before a request) the server exits with status 0. A request it cannot answer (a frame that is not
an ``.npy`` array, an array of the wrong dtype or shape, a stream that ends inside a request) ends it with one line
on stderr, ``lerobot-tar serve: <what is wrong>``, and status 1; so does a checkpoint it cannot load or serve (one
with images, or reading several observation steps, as Diffusion does: a request carries one). Anything the
libraries print while loading goes to stderr: stdout carries frames only.
"""

from __future__ import annotations

import io
import os
import struct
import sys
from pathlib import Path
from typing import BinaryIO

import numpy as np

__all__ = ["ChunkServer", "RequestError", "read_frame", "serve", "write_frame"]

#: The frame header: the payload's length in bytes, little-endian unsigned 64-bit.
HEADER = struct.Struct("<Q")
#: The largest payload read (1 GiB): a longer header is a broken stream, not a request.
MAX_FRAME = 1 << 30
STATE = "observation.state"
ENVIRONMENT = "observation.environment_state"


class RequestError(ValueError):
    """A request the server cannot answer (its one line on stderr)."""


def _read_exactly(stream: BinaryIO, n: int) -> bytes:
    data = bytearray()
    while len(data) < n:
        chunk = stream.read(n - len(data))
        if not chunk:
            break
        data += chunk
    return bytes(data)


def read_frame(stream: BinaryIO) -> np.ndarray | None:
    """The next frame's array; ``None`` at EOF before its header. ``RequestError`` for anything else."""
    header = _read_exactly(stream, HEADER.size)
    if not header:
        return None
    if len(header) < HEADER.size:
        raise RequestError("the stream ended inside a frame's header")
    (length,) = HEADER.unpack(header)
    if length > MAX_FRAME:
        raise RequestError(f"a frame of {length} bytes is announced; at most {MAX_FRAME} are read")
    payload = _read_exactly(stream, length)
    if len(payload) < length:
        raise RequestError(f"the stream ended inside a frame ({len(payload)} of {length} bytes)")
    try:
        return np.load(io.BytesIO(payload), allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise RequestError(f"a frame is not a NumPy .npy array without objects ({err})") from None


def write_frame(stream: BinaryIO, array: np.ndarray) -> None:
    """Write ``array`` as one frame and flush."""
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array), allow_pickle=False)
    payload = buffer.getvalue()
    stream.write(HEADER.pack(len(payload)) + payload)
    stream.flush()


class ChunkServer:
    """A checkpoint's policy and processors, answering ``chunks(observations, tasks) -> [N, H, A]``.

    Args:
        checkpoint: LeRobot's ``pretrained_model`` folder of any policy type (or the folder above it).
        device: where the policy runs (default ``cpu``).
    """

    def __init__(self, checkpoint: str | os.PathLike, device: str = "cpu"):
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors

        from .checkpoints import checkpoint_folder

        folder = checkpoint_folder(checkpoint)
        config = PreTrainedConfig.from_pretrained(folder)
        config.device = device
        self.policy = get_policy_class(config.type).from_pretrained(folder, config=config)
        self.policy.eval()
        self.preprocessor, self.postprocessor = make_pre_post_processors(
            self.policy.config,
            pretrained_path=str(folder),
            preprocessor_overrides={"device_processor": {"device": device}},
        )
        features = self.policy.config.input_features
        if STATE not in features:
            raise RequestError(f"{folder}: the policy reads no {STATE}; only state policies are served")
        self.state_dims = int(features[STATE].shape[0])
        self.environment_dims = int(features[ENVIRONMENT].shape[0]) if ENVIRONMENT in features else 0
        other = sorted(set(features) - {STATE, ENVIRONMENT})
        if other:
            raise RequestError(f"{folder}: the policy reads {other} besides the state; only state policies are served")
        if getattr(self.policy.config, "n_obs_steps", 1) != 1:
            raise RequestError(
                f"{folder}: the policy reads {self.policy.config.n_obs_steps} observation steps; a request carries "
                "one (policies reading one step are served: ACT, SmolVLA, pi0)"
            )
        self.action_dims = int(self.policy.config.output_features["action"].shape[0])
        self.horizon = int(self.chunks(np.zeros((1, self.observation_dims), np.float32), np.array([""]))[0].shape[0])

    @property
    def observation_dims(self) -> int:
        """``D``: the observation size a request carries."""
        return self.state_dims + self.environment_dims

    def chunks(self, observations: np.ndarray, tasks: np.ndarray) -> np.ndarray:
        """The unnormalised chunks ``[N, H, A]`` float32 for ``observations`` ``[N, D]`` and ``tasks`` ``[N]``."""
        import torch

        if observations.dtype != np.float32 or observations.ndim != 2 or observations.shape[1] != self.observation_dims:
            raise RequestError(
                f"observations must be float32 [N, {self.observation_dims}], got {observations.dtype} "
                f"{list(observations.shape)}"
            )
        if tasks.dtype.kind != "U" or tasks.shape != observations.shape[:1]:
            raise RequestError(
                f"tasks must be a unicode array [{observations.shape[0]}] (one per observation), got {tasks.dtype} "
                f"{list(tasks.shape)}"
            )
        obs = torch.from_numpy(observations.copy())
        batch = {STATE: obs[:, : self.state_dims], "task": [str(task) for task in tasks]}
        if self.environment_dims:
            batch[ENVIRONMENT] = obs[:, self.state_dims :]
        with torch.no_grad():
            chunk = self.postprocessor(self.policy.predict_action_chunk(self.preprocessor(batch)))
        return chunk.detach().to("cpu", torch.float32).numpy()


def serve(checkpoint: str | os.PathLike, stdin: BinaryIO, stdout: BinaryIO, device: str = "cpu") -> None:
    """Load ``checkpoint`` and answer requests from ``stdin`` on ``stdout`` until EOF (the module docstring).

    Raises:
        RequestError: a request it cannot answer; a checkpoint that is not a state policy.
    """
    server = ChunkServer(checkpoint, device)
    write_frame(stdout, np.array([server.observation_dims, server.horizon, server.action_dims], np.int64))
    while True:
        observations = read_frame(stdin)
        if observations is None:
            return
        tasks = read_frame(stdin)
        if tasks is None:
            raise RequestError("the stream ended after a request's observations, before its tasks")
        write_frame(stdout, server.chunks(observations, tasks))


def main(checkpoint: str, device: str = "cpu", threads: int | None = None) -> int:
    """``lerobot-tar serve``: frames on the process's stdout, everything else printed goes to stderr."""
    import torch

    from .checkpoints import CheckpointError

    if threads:
        torch.set_num_threads(threads)
    sys.stdout.flush()
    frames = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())  # what LeRobot prints cannot corrupt the frames
    try:
        serve(Path(checkpoint), sys.stdin.buffer, frames, device)
    except (RequestError, CheckpointError) as error:
        print(f"lerobot-tar serve: {error}", file=sys.stderr)
        return 1
    except Exception as error:  # the policy or its processors refused: still one line
        line = " ".join(f"{type(error).__name__}: {error}".split())
        print(f"lerobot-tar serve: {line}", file=sys.stderr)
        return 1
    finally:
        try:
            frames.close()
        except BrokenPipeError:  # the client is gone
            pass
    return 0
