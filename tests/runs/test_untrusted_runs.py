"""A run folder someone sends runs no code: a YAML payload in its ``config.yaml`` and a pickle payload in its
``checkpoint.pt`` are never executed by the commands that read run folders (report, eval, resume, ``init.from``),
which end with one line naming the file.
"""

from __future__ import annotations

from payload_helpers import run, torch_payload, yaml_payload
from run_helpers import ROLLOUTS, write_run


def test_no_file_of_a_run_folder_runs_code(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    received = write_run(tmp_path / "received", "tar", 0, ROLLOUTS[("tar", 0)], finished=None)
    (received / "config.yaml").write_text(yaml_payload(tmp_path / "code-ran-yaml"))
    (received / "checkpoint.pt").write_bytes(torch_payload(tmp_path / "code-ran-pickle"))
    ended = {
        "report": run(["report", str(received), "--out", str(tmp_path / "report")]),
        "eval": run(["eval", str(received), "--rollouts", "1", "--no-progress"]),
        "init.from": run(["train", f"init.from={received}", f"runs_root={tmp_path / 'runs'}"]),
        "resume": run(["train", f"run_dir={received}", "logging.progress=false"]),
    }
    assert sorted(p.name for p in tmp_path.glob("code-ran-*")) == []
    assert ended["report"].startswith("tar-rl report: ") and "config.yaml" in ended["report"], ended["report"]
    checkpoint = received / "checkpoint.pt"
    assert ended["eval"].startswith(f"tar-rl eval: {checkpoint} is not a readable tar-rl checkpoint"), ended["eval"]
    assert ended["init.from"].startswith(f"tar-rl train: init.from={received}: {checkpoint}"), ended["init.from"]
    assert ended["resume"].startswith(f"tar-rl train: {checkpoint} is not a readable"), ended["resume"]
    (received / "checkpoint.pt").unlink()  # a started run before its first checkpoint: known by its config.yaml
    resume = run(["train", f"run_dir={received}", "logging.progress=false"])
    assert resume.startswith(f"tar-rl train: {received / 'config.yaml'} cannot be read"), resume
    assert sorted(p.name for p in tmp_path.glob("code-ran-*")) == []
    assert not (tmp_path / "runs").exists()
