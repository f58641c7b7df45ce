"""``lerobot-tar serve``: a checkpoint's chunks on stdout for observations on stdin (the policy server tar-rl's
evaluator talks to), against the chunks computed by hand from the checkpoint's network and statistics; bad requests
refused in one line."""

from __future__ import annotations

import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tiny_checkpoint as tiny

SERVE = [str(Path(sys.executable).with_name("lerobot-tar")), "serve"]
TASKS = np.array(["Reach the goal position with the gripper.", "Push the puck to a goal."])


def frame(array) -> bytes:
    from lerobot_policy_tar.serve import write_frame

    buffer = io.BytesIO()
    write_frame(buffer, np.asarray(array))
    return buffer.getvalue()


def pickled_frame() -> bytes:
    """A frame holding an object array: loading it would unpickle."""
    from lerobot_policy_tar.serve import HEADER

    buffer = io.BytesIO()
    np.save(buffer, np.array([1, "a"], dtype=object), allow_pickle=True)
    return HEADER.pack(len(buffer.getvalue())) + buffer.getvalue()


def observations(n: int, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, tiny.STATE_DIMS + tiny.ENVIRONMENT_DIMS)).astype(np.float32)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    return tiny.write(tmp_path_factory.mktemp("tiny") / "pretrained_model", "act_tar")


def test_the_server_answers_the_policys_chunks_and_refuses_a_bad_request_in_one_line(checkpoint):
    from lerobot_policy_tar.serve import read_frame

    obs = observations(2)
    bad = frame(observations(1).astype(np.float64)) + frame(TASKS[:1])
    request = frame(obs) + frame(TASKS) + frame(obs[:1] + 1) + frame(TASKS[:1]) + bad
    done = subprocess.run([*SERVE, str(checkpoint.parent), "--threads=1"], input=request, capture_output=True)
    replies = io.BytesIO(done.stdout)
    hello, first, second = read_frame(replies), read_frame(replies), read_frame(replies)
    assert read_frame(replies) is None  # nothing else on stdout: LeRobot's prints went to stderr
    assert hello.tolist() == [tiny.STATE_DIMS + tiny.ENVIRONMENT_DIMS, tiny.HORIZON, tiny.ACTION_DIMS]
    assert first.dtype == np.float32 and first.shape == (2, tiny.HORIZON, tiny.ACTION_DIMS)
    np.testing.assert_allclose(first, tiny.chunks(checkpoint, obs, TASKS.tolist()), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(second, tiny.chunks(checkpoint, obs[:1] + 1, TASKS[:1].tolist()), rtol=1e-5, atol=1e-5)
    assert not np.allclose(first[0], first[1])  # the observations reach the network
    assert done.returncode == 1
    errors = [line for line in done.stderr.decode().splitlines() if line.startswith("lerobot-tar serve:")]
    assert errors == ["lerobot-tar serve: observations must be float32 [N, 39], got float64 [1, 39]"]
    assert done.stderr.decode().rstrip("\n").endswith(errors[0])


def test_the_server_ends_at_eof(checkpoint):
    from lerobot_policy_tar.serve import read_frame, serve

    obs, replies = observations(2), io.BytesIO()
    serve(checkpoint, io.BytesIO(frame(obs) + frame(TASKS)), replies)  # returns: no error at EOF
    replies.seek(0)
    read_frame(replies)
    np.testing.assert_allclose(read_frame(replies), tiny.chunks(checkpoint, obs, TASKS.tolist()), rtol=1e-5, atol=1e-5)
    assert read_frame(replies) is None


@pytest.mark.parametrize(
    ("request_bytes", "message"),
    [
        (frame(observations(2)[:, :5]) + frame(TASKS), r"observations must be float32 \[N, 39\], got float32 \[2, 5\]"),
        (frame(observations(2)) + frame(TASKS[:1]), r"tasks must be a unicode array \[2\] .*got <U41 \[1\]"),
        (frame(observations(2)) + frame(np.arange(2)), r"tasks must be a unicode array \[2\]"),
        (frame(observations(2)), "the stream ended after a request's observations"),
        (frame(observations(2))[:20], "the stream ended inside a frame"),
        (b"\x05\x00\x00\x00\x00\x00\x00\x00hello", "a frame is not a NumPy .npy array without objects"),
        (pickled_frame(), "a frame is not a NumPy .npy array without objects"),
    ],
    ids=["shape", "task-count", "task-dtype", "no-tasks", "truncated", "not-npy", "pickled"],
)
def test_requests_the_server_refuses(checkpoint, request_bytes, message):
    from lerobot_policy_tar.serve import RequestError, serve

    replies = io.BytesIO()
    with pytest.raises(RequestError, match=message):
        serve(checkpoint, io.BytesIO(request_bytes), replies)
    assert replies.getvalue()  # the hello came first


def test_a_folder_that_is_not_a_checkpoint_is_refused(tmp_path):
    from lerobot_policy_tar.checkpoints import CheckpointError
    from lerobot_policy_tar.serve import serve

    replies = io.BytesIO()
    with pytest.raises(CheckpointError, match=r"is not a LeRobot policy checkpoint: it has no config\.json"):
        serve(tmp_path, io.BytesIO(), replies)
    assert replies.getvalue() == b""
