"""The command line's persistent compilation cache (diffshade.compile_cache).

JAX decides once per process whether it uses a cache, at the first compilation, so each
behaviour is checked in a fresh interpreter: the files that appear in the cache folder,
and JAX's own log of a cache hit in a second process. (The test session itself runs with
DIFFSHADE_COMPILE_CACHE=0, set in conftest.py, so in-process CLI tests write nothing
into the user's cache.)"""

import os
import subprocess
import sys
from pathlib import Path

from diffshade import cli, compile_cache

ROOT = Path(__file__).resolve().parent.parent

# Enables the cache as the CLI does, compiles one program, prints the folder enable() chose.
SCRIPT = """
import jax
from diffshade import compile_cache
print(compile_cache.enable())
jax.jit(lambda x: x * 2.0 + 1.0)(jax.numpy.arange(3.0)).block_until_ready()
"""


def run(tmp_path, **env):
    """(stdout, stderr) of SCRIPT in a fresh interpreter, with env on top of a clean one."""
    base = {k: v for k, v in os.environ.items()
            if not k.startswith(("DIFFSHADE_COMPILE_CACHE", "JAX_COMPILATION_CACHE"))}
    base["PYTHONPATH"] = os.pathsep.join([str(ROOT), base.get("PYTHONPATH", "")])
    done = subprocess.run([sys.executable, "-c", SCRIPT], env=base | env, cwd=tmp_path,
                          capture_output=True, text=True, check=True)
    return done.stdout.strip(), done.stderr


def files(path):
    return [p for p in Path(path).rglob("*") if p.is_file()] if Path(path).exists() else []


def test_cache_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv("DIFFSHADE_COMPILE_CACHE_DIR", raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert compile_cache.cache_dir() == str(tmp_path / ".cache" / "diffshade" / "jax")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compile_cache.cache_dir() == str(tmp_path / "xdg" / "diffshade" / "jax")
    monkeypatch.setenv("DIFFSHADE_COMPILE_CACHE_DIR", "~/mine")
    assert compile_cache.cache_dir() == str(tmp_path / "mine")


def test_a_second_process_loads_what_the_first_compiled(tmp_path):
    cache = tmp_path / "cache"
    shown, _ = run(tmp_path, DIFFSHADE_COMPILE_CACHE_DIR=str(cache))
    assert shown == str(cache)
    written = files(cache)
    assert written, "nothing was written to the cache"
    _, log = run(tmp_path, DIFFSHADE_COMPILE_CACHE_DIR=str(cache), JAX_LOG_COMPILES="1")
    assert "Persistent compilation cache hit" in log
    assert sorted(files(cache)) == sorted(written)


def test_switched_off_it_writes_nothing(tmp_path):
    shown, _ = run(tmp_path, DIFFSHADE_COMPILE_CACHE="0", XDG_CACHE_HOME=str(tmp_path / "xdg"),
                   HOME=str(tmp_path))
    assert shown == "None"
    assert files(tmp_path) == []


def test_a_cache_folder_set_for_jax_is_kept(tmp_path):
    shown, _ = run(tmp_path, JAX_COMPILATION_CACHE_DIR=str(tmp_path / "jax"),
                   JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
                   DIFFSHADE_COMPILE_CACHE_DIR=str(tmp_path / "ours"))
    assert shown == str(tmp_path / "jax")
    assert files(tmp_path / "jax") and not files(tmp_path / "ours")


def test_the_command_line_enables_it_first(monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(compile_cache, "enable", lambda: calls.append("enable"))
    assert cli.main(["--help"]) == 0
    assert calls == ["enable"]
