"""Item 8, untrusted data: nothing read from fixtures, cassettes or caches is unpickled or evaluated.

* Static: every module under src/ is parsed (ast) and searched for the ways Python runs data as code:
  pickle-family imports (pickle, dill, cloudpickle, marshal, shelve, joblib, jsonpickle), eval/exec/compile,
  yaml.load without a safe loader, np.load with allow_pickle not False, torch.load without weights_only=True,
  pandas.read_pickle, and a diskcache store opened without a disk class of our own (diskcache's default
  disk pickles anything that is not a plain str/bytes/int/float). The checker is itself tested on snippets
  that must and must not be flagged, so a regression in it cannot pass silently.
* Dynamic: live pickles planted where a person or a damaged disk could put them (a response-cache value
  and key, an embedding-cache row, an object array in steps.npz) are refused with a clear message and never
  run: each payload would create a marker file when unpickled, and no marker appears.
* The HTML report: a model answer full of markup (``<script>``, an ``<img onerror>``) reaches the
  transcripts verbatim and comes out of ``vlmproprio report`` as text, never as markup.
"""

from __future__ import annotations

import ast
import io
import pickle
import sqlite3
import zipfile
from pathlib import Path

import numpy as np
import pytest
from fault_support import cli_in_process
from reliability_support import (
    REPO,
    assert_one_line_error,
    cache_rows,
    cli,
    fixture_subset,
    set_cache_row,
    transcripts_of,
)

SRC = REPO / "src"
PICKLE_MODULES = {"pickle", "cPickle", "_pickle", "dill", "cloudpickle", "marshal", "shelve", "joblib", "jsonpickle"}
SAFE_YAML_LOADERS = {"SafeLoader", "CSafeLoader", "BaseLoader", "CBaseLoader"}
CODE_RUNNERS = {"eval", "exec", "compile", "builtins.eval", "builtins.exec"} | {
    f"yaml.{f}" for f in ("unsafe_load", "full_load", "unsafe_load_all", "full_load_all")
}
DISKCACHE_STORES = {"Cache", "FanoutCache", "Index", "Deque", "DjangoCache"}


def _dotted(node: ast.AST) -> str:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return f"{_dotted(node.value)}.{node.attr}"
    return ""


def _kw(call: ast.Call, name: str) -> ast.expr | None:
    return next((k.value for k in call.keywords if k.arg == name), None)


def _is_const(node: ast.expr | None, value: object) -> bool:
    return isinstance(node, ast.Constant) and node.value is value


def unsafe_uses(source: str, filename: str = "<snippet>") -> list[str]:
    """Every place in ``source`` that could run data as code, as 'file:line: what'."""
    found = []
    for node in ast.walk(ast.parse(source, filename)):
        where = f"{filename}:{getattr(node, 'lineno', 0)}"
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            for name in names:
                if name.split(".")[0] in PICKLE_MODULES:
                    found.append(f"{where}: imports {name}")
        if not isinstance(node, ast.Call):
            continue
        func = _dotted(node.func)
        last = func.rsplit(".", 1)[-1]
        if func in CODE_RUNNERS:
            found.append(f"{where}: calls {func}")
        elif func in ("yaml.load", "yaml.load_all"):
            loader = _kw(node, "Loader") or (node.args[1] if len(node.args) > 1 else None)
            if loader is None or _dotted(loader).rsplit(".", 1)[-1] not in SAFE_YAML_LOADERS:
                found.append(f"{where}: {func} without a safe Loader")
        elif func in ("np.load", "numpy.load"):
            allow = _kw(node, "allow_pickle")
            if allow is not None and not _is_const(allow, False):
                found.append(f"{where}: {func} with allow_pickle not False")
        elif func == "torch.load" and not _is_const(_kw(node, "weights_only"), True):
            found.append(f"{where}: torch.load without weights_only=True")
        elif last == "read_pickle" or func.endswith(("pickle.load", "pickle.loads")):
            found.append(f"{where}: calls {func}")
        elif func.startswith("diskcache.") and last in DISKCACHE_STORES and _kw(node, "disk") is None:
            found.append(f"{where}: {func} with diskcache's pickling default disk")
    return found


def test_no_module_in_src_can_run_data_as_code(figures):
    files = sorted(SRC.rglob("*.py"))
    assert len(files) > 20
    problems = [p for f in files for p in unsafe_uses(f.read_text(encoding="utf-8"), str(f.relative_to(REPO)))]
    assert problems == []
    figures("untrusted data: static", modules_parsed=len(files), unsafe_uses=len(problems))


@pytest.mark.parametrize(
    ("snippet", "flagged"),
    [
        ("import pickle", True),
        ("from dill import loads", True),
        ("import marshal", True),
        ("x = eval(s)", True),
        ("exec(code)", True),
        ("compile(src, 'f', 'exec')", True),
        ("yaml.load(f)", True),
        ("yaml.load(f, Loader=yaml.Loader)", True),
        ("yaml.load(f, Loader=yaml.SafeLoader)", False),
        ("yaml.unsafe_load(f)", True),
        ("yaml.safe_load(f)", False),
        ("np.load(p, allow_pickle=True)", True),
        ("np.load(p, allow_pickle=flag)", True),
        ("np.load(p, allow_pickle=False)", False),
        ("np.load(p)", False),
        ("torch.load(p)", True),
        ("torch.load(p, weights_only=False)", True),
        ("torch.load(p, weights_only=True)", False),
        ("pd.read_pickle(p)", True),
        ("diskcache.Cache(d)", True),
        ("diskcache.Cache(d, disk=JSONOnlyDisk)", False),
        ("model.eval()", False),
        ("json.loads(s)", False),
    ],
)
def test_the_checker_flags_what_it_must(snippet, flagged):
    assert bool(unsafe_uses(snippet)) is flagged


# ---------------------------------------------------------------------------------------------- live payloads


class Payload:
    """Unpickling this creates ``marker``: proof that a pickle was run."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _payload(marker: Path) -> bytes:
    blob = pickle.dumps(Payload(marker))
    pickle.loads(blob).close()  # live: it does create the marker ...
    assert marker.exists()
    marker.unlink()  # ... so its absence later means it never ran
    return blob


@pytest.fixture
def reference_run(tmp_path):
    fixtures = fixture_subset(tmp_path / "fixtures", ["door_04"])
    args = ["run", "--model", "reference", "--fixtures", fixtures, "--conditions", "ee", "--no-progress"]
    args += ["--cache-dir", tmp_path / "cache"]
    proc = cli_in_process([*args, "--out", tmp_path / "clean"])  # the clean run: its output is not checked
    assert proc.returncode == 0, proc.stderr
    return tmp_path, args


def test_a_pickle_planted_as_a_cache_value_is_refused_and_recomputed(reference_run, figures):
    tmp, args = reference_run
    marker = tmp / "pwned-value"
    rows = cache_rows(tmp / "cache")
    key = sorted(rows)[0]
    set_cache_row(tmp / "cache", rows[key][0], _payload(marker), mode=4)  # diskcache's MODE_PICKLE
    proc = cli([*args, "--out", tmp / "again"])
    assert proc.returncode == 0, proc.stderr
    assert f"entry {key}: cache value has storage mode 4 (refusing to unpickle)" in proc.stderr
    assert transcripts_of(tmp / "again") == transcripts_of(tmp / "clean")
    assert not marker.exists()
    figures("untrusted data: planted pickles", planted=1, refused=1, executed=0)


def test_a_pickle_planted_as_a_cache_key_is_refused(reference_run, figures):
    tmp, args = reference_run
    marker = tmp / "pwned-key"
    with sqlite3.connect(tmp / "cache" / "cache.db") as conn:
        cols = [r[1] for r in conn.execute("PRAGMA table_info(Cache)")]
        row = dict(zip(cols, conn.execute("SELECT * FROM Cache LIMIT 1").fetchone(), strict=True))
        row.pop("rowid", None)
        row.update(key=_payload(marker), raw=0)  # raw=0: diskcache unpickles the key
        conn.execute(f"INSERT INTO Cache ({', '.join(row)}) VALUES ({', '.join('?' * len(row))})", list(row.values()))
    proc = cli(["cassette", "export", "--model", "reference", "--cache", tmp / "cache", "--out", tmp / "x.jsonl"])
    assert_one_line_error(proc, "cache key is not raw JSON bytes (refusing to unpickle)")
    proc = cli([*args, "--out", tmp / "again"])  # lookups by key never meet the planted row
    assert proc.returncode == 0, proc.stderr
    assert not marker.exists()
    figures("untrusted data: planted pickles", planted=1, refused=1, executed=0)


def test_a_pickle_planted_in_the_embedding_cache_is_refused(tmp_path, figures):
    from vlmproprio.embeddings import EmbeddingError, EmbeddingStore, text_key

    marker = tmp_path / "pwned-embedding"
    with EmbeddingStore(tmp_path / "emb") as store:
        store.put_many("enc", {"a caption": np.ones(4, dtype=np.float32)})
    with sqlite3.connect(tmp_path / "emb" / "cache.db") as conn:
        (key,) = conn.execute("SELECT key FROM Cache").fetchone()
        assert key == text_key("enc", "a caption")  # the one row, the one read below
        conn.execute("UPDATE Cache SET value = ?, mode = 4", (_payload(marker),))
    with EmbeddingStore(tmp_path / "emb") as store, pytest.raises(EmbeddingError, match="mode 4 refused"):
        store.get_many("enc", ["a caption"])
    assert not marker.exists()
    figures("untrusted data: planted pickles", planted=1, refused=1, executed=0)


def test_an_object_array_in_steps_npz_is_refused(tmp_path, figures):
    from vlmproprio.episodes import EpisodeError, load_episode, write_manifest

    fixtures = fixture_subset(tmp_path / "fixtures", ["door_04"])
    marker = tmp_path / "pwned-npz"
    steps = fixtures / "episodes" / "door_04" / "steps.npz"
    with np.load(steps, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    evil = np.empty(len(arrays["step"]), dtype=object)
    evil[:] = [Payload(marker)] * len(evil)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, arr in arrays.items():
            member = io.BytesIO()
            np.save(member, evil if name == "joints" else arr, allow_pickle=True)
            zf.writestr(f"{name}.npy", member.getvalue())
    steps.write_bytes(buf.getvalue())
    write_manifest(fixtures)  # the manifest blesses it: only the reader stands in the way
    with pytest.raises(EpisodeError, match=r"steps\.npz: cannot read full-rate states"):
        _ = load_episode(fixtures, "door_04").step_states  # loading reads (and checks) steps.npz
    assert not marker.exists()
    figures("untrusted data: planted pickles", planted=1, refused=1, executed=0)


def test_report_renders_html_in_captions_as_text(tmp_path, monkeypatch):
    """Captions with markup, scored and reported by the CLI as a user would: the page shows them as text.

    The CLI runs in this process: what is checked is the pages it writes, and scoring in a subprocess imported
    torch and the encoder again (~10 CPU s) where the test session usually has them already."""
    from vlmproprio.testing.openai_server import FakeOpenAIServer

    pytest.importorskip("openai", reason="the run goes through the openai backend")
    evil = '<script>alert("x")</script><img src=x onerror=alert(1)>'
    fixtures = fixture_subset(tmp_path / "fixtures", ["door_04"])
    with FakeOpenAIServer(responder=lambda body: f"Frame 1: {evil}\nFrame 2: {evil}") as server:
        args = ["run", "--model", "openai:fake-vlm", "--base-url", server.base_url, "--fixtures", fixtures]
        args += ["--conditions", "none", "--frame-stride", "3", "--no-progress", "--out", tmp_path / "run"]
        proc = cli_in_process([*args, "--cache-dir", tmp_path / "cache"])
    assert proc.returncode == 0, proc.stderr
    captions = [f["text"] for t in transcripts_of(tmp_path / "run").values() for f in t["frames"]]
    assert evil in captions  # the markup reached the transcripts verbatim: the report is what must escape it
    monkeypatch.setenv("VLMPROPRIO_CACHE", str(tmp_path / "cache-root"))  # its embedding cache, not the user's
    proc = cli_in_process(["report", tmp_path / "run"])  # scores the run first (the default encoder)
    assert proc.returncode == 0, proc.stderr
    pages = [p.read_text(encoding="utf-8") for p in (tmp_path / "run" / "report").rglob("*.html")]
    assert pages and not any("<script>alert" in page or "<img src=x" in page for page in pages)
    assert any("&lt;script&gt;" in page for page in pages)
