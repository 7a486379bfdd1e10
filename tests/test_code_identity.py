"""The code's identity (harness/runs/identity.py) means the code: git names it only when
git holds the project itself, and "dirty" means changed code, never another file.

Each case builds a real git repository in a temporary directory and points
:data:`harness.runs.identity.ROOT` (the directory that holds the packages) into it.
"""

import json
import os
import subprocess
from pathlib import Path

import pytest

from harness.runs import identity

SMALL = ["grid.n=8", "agents.n=50", "sim.t_final=0.06", "sim.dt=0.02", "log.progress=off"]


def git(repo: Path, *args: str) -> str:
    """Run git in ``repo`` as a user would (no outer ``GIT_*`` variables)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")}
    cmd = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t", *args]
    return subprocess.run(cmd, check=True, capture_output=True, text=True, env=env).stdout.strip()


def checkout(root: Path, files: dict[str, str]) -> str:
    """A git repository at ``root`` holding ``files`` (path -> text) in one commit; the
    commit.
    """
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    root.mkdir(parents=True, exist_ok=True)
    git(root, "init", "-q")
    git(root, "add", "--", *files)
    git(root, "commit", "-qm", "one")
    return git(root, "rev-parse", "HEAD")


PROJECT = {
    "harness/law.py": "ALPHA = 1\n",
    "conf/closed_loop.yaml": "seed: 0\n",
    "README.md": "the project\n",
}


@pytest.mark.parametrize(
    "inside", ["vendor/densityloop", ".venv/lib/python3.11/site-packages"], ids=["copy", "venv"]
)
def test_a_copy_of_the_project_inside_another_checkout_is_identified_by_its_own_code(
    tmp_path, monkeypatch, inside
):
    outer = tmp_path / "other"
    commit = checkout(outer, {".gitignore": f"{inside.split('/')[0]}/\n", "main.c": "int x;\n"})
    copy = outer / inside
    for name, text in PROJECT.items():
        (copy / name).parent.mkdir(parents=True, exist_ok=True)
        (copy / name).write_text(text)
    monkeypatch.setattr(identity, "ROOT", copy)
    before = identity.code_identity()
    assert before["git_commit"] != commit and before["git_commit"] == "unknown"
    assert before["git_dirty"] == "unknown"
    assert before["git_diff_sha256"].startswith("source:")
    (copy / "harness" / "law.py").write_text("ALPHA = 2\n")  # the copy edited
    after = identity.code_identity()
    assert after["code_sha256"] != before["code_sha256"]
    assert "git_diff_sha256" in identity.code_change(before, after)


def test_a_resumed_sweep_of_an_edited_copy_reruns_its_jobs_and_is_not_pooled(
    tmp_path, monkeypatch, compose, capsys
):
    from analysis import sweep
    from harness.runs.app import run_job

    outer = tmp_path / "other"
    checkout(outer, {".gitignore": "vendor/\n", "main.c": "int x;\n"})
    copy = outer / "vendor" / "densityloop"
    for name, text in PROJECT.items():
        (copy / name).parent.mkdir(parents=True, exist_ok=True)
        (copy / name).write_text(text)
    monkeypatch.setattr(identity, "ROOT", copy)
    jobs = {"a": compose(SMALL), "b": compose([*SMALL, "seed=3"])}
    sweep_dir = tmp_path / "sweep"

    def resume(names):
        for k, name in enumerate(names):
            run_job(jobs[name], sweep_dir / name, k, [name])
        return {
            n: json.loads((sweep_dir / n / "job_status.json").read_text())["runs"] for n in jobs
        }

    assert resume("ab") == {"a": 1, "b": 1}
    (copy / "harness" / "law.py").write_text("ALPHA = 2\n")
    assert resume("b") == {"a": 1, "b": 2}  # half the sweep resumed with the new code
    capsys.readouterr()
    assert sweep.main([str(sweep_dir)]) == 2  # old and new code are not one study
    assert "different code" in capsys.readouterr().err
    assert resume("ab") == {"a": 2, "b": 2}


def test_files_that_are_not_code_leave_the_code_clean(tmp_path, monkeypatch, compose):
    from harness.runs.app import run_job

    repo = tmp_path / "code"
    commit = checkout(repo, {**PROJECT, ".gitignore": "outputs/\n"})
    monkeypatch.setattr(identity, "ROOT", repo)
    clean = identity.code_identity()
    assert (clean["git_commit"], clean["git_dirty"], clean["git_diff_sha256"]) == (
        commit,
        "false",
        "clean",
    )
    out = repo / "outputs" / "sweep" / "a"
    monkeypatch.chdir(repo)  # a relative floor cache: inside the checkout, untracked
    cfg = compose([*SMALL, "log.floor_cache=floors"])
    run_job(cfg, out, 0, ["a"])
    assert list((repo / "floors").iterdir()), "the floor cache was not written in the checkout"
    (repo / "NOTES.txt").write_text("to do\n")  # an untracked note
    (repo / "README.md").write_text("the project, explained\n")  # documentation edited
    run_job(cfg, out, 0, ["a"])  # resumed
    now = identity.code_identity()
    assert (now["git_dirty"], now["git_diff_sha256"]) == ("false", "clean")
    assert now["code_sha256"] == clean["code_sha256"]
    status = json.loads((out / "job_status.json").read_text())
    assert status["runs"] == 1 and status["skipped"] is True, status


@pytest.mark.parametrize(
    "change",
    ["edit", "untracked", "ignored", "config", "staged", "deleted"],
)
def test_changed_code_makes_the_checkout_dirty(tmp_path, monkeypatch, change):
    repo = tmp_path / "code"
    checkout(repo, {**PROJECT, ".gitignore": "harness/generated_*.py\n"})
    monkeypatch.setattr(identity, "ROOT", repo)
    clean = identity.code_identity()
    if change == "edit":
        (repo / "harness" / "law.py").write_text("ALPHA = 2\n")
    elif change == "untracked":
        (repo / "harness" / "new_law.py").write_text("BETA = 1\n")
    elif change == "ignored":  # ignoring a code file does not make it less the code
        (repo / "harness" / "generated_law.py").write_text("GAMMA = 1\n")
    elif change == "config":
        (repo / "conf" / "control").mkdir()
        (repo / "conf" / "control" / "mine.yaml").write_text("alpha: 1\n")
    elif change == "staged":  # in the index, not in the commit
        (repo / "harness" / "new_law.py").write_text("BETA = 1\n")
        git(repo, "add", "harness/new_law.py")
    else:
        (repo / "harness" / "law.py").unlink()
    now = identity.code_identity()
    assert now["git_dirty"] == "true" and now["git_diff_sha256"] != "clean"
    assert now["code_sha256"] != clean["code_sha256"]


@pytest.mark.parametrize("flag", ["--skip-worktree", "--assume-unchanged"])
def test_an_edit_under_an_index_flag_makes_the_checkout_dirty(tmp_path, monkeypatch, flag):
    repo = tmp_path / "code"
    checkout(repo, PROJECT)
    monkeypatch.setattr(identity, "ROOT", repo)
    clean = identity.code_identity()
    git(repo, "update-index", flag, "harness/law.py")  # git diff no longer looks at it
    assert identity.code_identity() == clean  # the flag alone changes no code
    law = repo / "harness" / "law.py"
    law.write_text("ALPHA = 2\n")
    edited = identity.code_identity()
    assert (edited["git_dirty"], edited["git_diff_sha256"] != "clean") == ("true", True)
    assert edited["code_sha256"] != clean["code_sha256"]
    law.write_text("ALPHA = 3\n")  # the flagged file edited again: other code
    again = identity.code_identity()
    assert again["code_sha256"] not in (clean["code_sha256"], edited["code_sha256"])
    law.write_text("ALPHA = 1\n")  # the commit's bytes again
    assert identity.code_identity() == clean


NOISE = '#!/bin/sh\n[ -n "$1" ] && cat "$1"\ndate +%s%N\nod -An -N8 -tx1 /dev/urandom\n'
"""A diff tool or text conversion whose output changes on every call."""


@pytest.mark.parametrize("setting", ["diff.external", "textconv", "color", "user-diff.external"])
def test_the_users_git_configuration_never_enters_the_code_identity(tmp_path, monkeypatch, setting):
    repo = tmp_path / "code"
    checkout(repo, PROJECT)
    monkeypatch.setattr(identity, "ROOT", repo)
    (repo / "harness" / "law.py").write_text("ALPHA = 2\n")
    plain = identity.code_identity()
    noise = tmp_path / "noise.sh"
    noise.write_text(NOISE)
    noise.chmod(0o755)
    if setting == "diff.external":
        git(repo, "config", "diff.external", str(noise))
    elif setting == "textconv":
        (repo / ".git" / "info" / "attributes").write_text("*.py diff=noise\n")
        git(repo, "config", "diff.noise.textconv", str(noise))
    elif setting == "color":
        git(repo, "config", "color.diff", "always")
        git(repo, "config", "color.ui", "always")
    else:  # in the user's own configuration (~/.gitconfig)
        home = tmp_path / "home"
        home.mkdir()
        (home / ".gitconfig").write_text(f"[diff]\n\texternal = {noise}\n")
        monkeypatch.setenv("HOME", str(home))
        monkeypatch.delenv("XDG_CONFIG_HOME", raising=False)
    first, second = identity.code_identity(), identity.code_identity()
    assert first == second == plain


def test_a_fifo_among_the_code_files_enters_the_identity_unopened(tmp_path, monkeypatch):
    repo = tmp_path / "code"
    checkout(repo, PROJECT)
    os.mkfifo(repo / "harness" / "pipe.py")
    monkeypatch.setattr(identity, "ROOT", repo)
    assert identity.code_identity()["git_commit"] != "unknown"  # git lists no FIFO
    (repo / ".git").rename(repo / "git.moved")  # no git: the source files are read
    source = identity.code_identity()["git_diff_sha256"]  # returns: the FIFO is not opened
    assert source.startswith("source:")
    (repo / "harness" / "pipe.py").unlink()
    assert identity.code_identity()["git_diff_sha256"] != source


def test_the_identity_of_this_checkout_is_its_git_commit_when_git_holds_it():
    root = Path(__file__).resolve().parents[1]
    assert identity.ROOT == root
    top = subprocess.run(
        ["git", "-C", str(root), "rev-parse", "--show-toplevel"], capture_output=True, text=True
    )
    if top.returncode != 0 or Path(top.stdout.strip()).resolve() != root:
        pytest.skip("this copy of the project is not a git checkout of its own")
    head = git(root, "rev-parse", "HEAD")
    assert identity.code_identity()["git_commit"] == head
