"""Issue 36, items 2 and 3: every credential the suite is given is masked in every encoding it sends.

The credentials come in several shapes: a user and password in the server URL (``--base-url`` or
``OPENAI_BASE_URL``), which the HTTP layer sends as ``Authorization: Basic base64(user:password)``; an API key
of digits only; a query parameter that carries a secret (``?code=``, ``?sig=``, ``?api_key=`` ...). A server
that quotes back what it was sent (FakeOpenAIServer(echo_credentials=True): the header, its credential, the
decoded ``user:password``, the password, the query and its values) puts each of them into answers and error
messages. End to end: runs through that server (record, live, a run that fails on it), then ``score`` and
``report``; every file under the sandbox (transcripts, cache, cassette, audit.json, frames.csv, the report) and
every console line is searched for each encoding: raw, URL-quoted, ``user:password``, its base64 (padded or
not). The scrubber itself is checked on each shape given each way (flag, environment variable, proxy).

Before this, only the Bearer form and URL-shaped credentials were masked: a quoted Basic credential, the
password alone, a digits-only key and a ``?code=`` value reached the console and the files.
"""

from __future__ import annotations

import base64
import secrets
from pathlib import Path
from urllib.parse import quote

import pytest
from fast_support import forked_cli
from fault_support import cli_in_process
from reliability_support import all_files, cache_env_sharing_embeddings, caption_responder, fixture_subset

from extras import needs_openai
from vlmproprio.secrets import scrub
from vlmproprio.testing.openai_server import FakeOpenAIServer

# checked, not imported: collecting this module on every xdist worker must not cost the SDK's ~1 CPU s
pytestmark = needs_openai

MODEL = "openai:fake-vlm"
RUN_ARGS = ("--model", MODEL, "--episodes", "door_00", "--conditions", "none,both", "--frame-stride", "3")
# query parameters that carry a secret, by the services that use them
SECRET_PARAMS = (
    "code",  # OAuth authorisation code, Azure Functions' function key
    "key",  # Google APIs
    "api_key",
    "apikey",
    "token",
    "access_token",
    "sig",  # Azure SAS
    "signature",
    "X-Amz-Signature",  # S3 presigned URLs
    "X-Amz-Security-Token",
    "password",
    "secret",
    "client_secret",
    "oauth_signature",
    "x-functions-key",  # Azure Functions
    "subscription-key",  # Azure API Management
    "private_token",  # GitLab
)


def _password() -> str:
    """A password with characters a URL must quote (@ / : !), so the quoted and the sent form differ."""
    return f"Pw{secrets.token_hex(8)}@/:!"


def _forms(user: str, password: str) -> list[str]:
    """Each encoding of a URL credential the HTTP layer sends or a server may quote back."""
    pair = f"{user}:{password}"
    b64 = base64.b64encode(pair.encode()).decode()
    return [password, quote(password, safe=""), pair, b64, b64.rstrip("="), f"{user}:{quote(password, safe='')}"]


def _url(base: str, user: str, password: str) -> str:
    scheme, rest = base.split("://", 1)
    return f"{scheme}://{user}:{quote(password, safe='')}@{rest}"


def _digits_key() -> str:
    return str(secrets.randbelow(10**20) + 10**20)  # 21 digits


# ---------------------------------------------------------------------------------------------- the scrubber


@pytest.mark.parametrize("given_as", ["--base-url", "OPENAI_BASE_URL", "HTTPS_PROXY"])
def test_url_credentials_are_masked_in_every_encoding(given_as, monkeypatch):
    from vlmproprio.backends.openai import OpenAIBackend

    user, password = f"user{secrets.token_hex(3)}", _password()
    url = _url("http://vlm.example:8000/v1", user, password)
    monkeypatch.setenv("OPENAI_API_KEY", "sk-" + secrets.token_hex(16))
    if given_as == "--base-url":
        OpenAIBackend("fake-vlm", base_url=url)  # as the CLI and the benchmark build it
    else:
        monkeypatch.setenv(given_as, url)
    for form in _forms(user, password):
        out = scrub(f"the server says {form} (quoted)")
        assert form not in out and "***" in out, (given_as, form, out)
    out = scrub(f"Authorization: Basic {_forms(user, password)[3]}; password {password}")
    assert password not in out and _forms(user, password)[3] not in out
    clean = "The gripper opens the door; F1 0.65 at threshold 0.65, user study, password-free."
    assert scrub(clean) == clean


@pytest.mark.parametrize("name", SECRET_PARAMS)
def test_secret_query_parameters_are_masked_in_urls_and_alone(name, monkeypatch):
    from vlmproprio.backends.openai import OpenAIBackend

    value = secrets.token_urlsafe(12)
    url = f"https://vlm.example/v1?page=2&{name}={value}&lang=en"
    line = scrub(f"cannot reach {url}: is the server running?")
    assert value not in line and f"{name}=***" in line and "page=2" in line and "lang=en" in line
    monkeypatch.setenv("OPENAI_API_KEY", "sk-" + secrets.token_hex(16))
    OpenAIBackend("fake-vlm", base_url=url)
    assert value not in scrub(f"the server quoted {value} back")  # the value alone, once given


@pytest.mark.parametrize("variable", ["OPENAI_API_KEY", "MY_SERVER_PIN"])
def test_a_digits_only_key_is_masked(variable, monkeypatch):
    from vlmproprio.backends.openai import OpenAIBackend

    key = _digits_key()
    monkeypatch.setenv(variable, key)
    OpenAIBackend("fake-vlm", base_url="http://127.0.0.1:9/v1", api_key_env=variable)
    b64 = base64.b64encode(key.encode()).decode()
    for text in (f"echo {key}", f"Authorization: Bearer {key}", f"credential {key}.", f"b64 {b64}"):
        out = scrub(text)
        assert key not in out and b64 not in out, out
    assert scrub("F1 0.65234 over 1200345 frames") == "F1 0.65234 over 1200345 frames"  # numbers stay


# ---------------------------------------------------------------------------------------------- end to end

_LOGS: list[Path] = []


@pytest.fixture(scope="module")
def echoed(tmp_path_factory):
    """Runs through a server that quotes every credential back, scored and reported, with all their output."""
    root = tmp_path_factory.mktemp("secret-shapes")
    _LOGS[:] = [root / "logs"]
    fixtures = fixture_subset(root / "fixtures", ["door_00"])
    env = cache_env_sharing_embeddings(root, tmp_path_factory)
    key = _digits_key()
    env["OPENAI_API_KEY"] = key
    (user_a, pw_a), (user_b, pw_b) = (f"alice{secrets.token_hex(2)}", _password()), ("bob", _password())
    code = secrets.token_urlsafe(12)
    outputs: list[str] = []

    def vp(args, extra_env=None, **kw):
        proc = forked_cli([*args, "--no-progress"], _LOGS[0], env={**env, **(extra_env or {})}, **kw)
        outputs.extend([proc.stdout, proc.stderr])
        return proc

    runs = {}
    with FakeOpenAIServer(responder=caption_responder, echo_credentials=True) as server:
        common = [*RUN_ARGS, "--fixtures", fixtures, "--concurrency", "1"]
        # --base-url with a user and password: sent as Basic; a 500 on the way (retried) quotes it too
        server.inject("500", retry_after=0.01)
        runs["basic"] = root / "run-basic"
        proc = vp(["run", *common, "--base-url", _url(server.base_url, user_a, pw_a), "--mode", "record",
                   "--out", runs["basic"]])  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-3000:]
        # OPENAI_BASE_URL with credentials, no --base-url
        runs["env"] = root / "run-env"
        proc = vp(
            ["run", *common, "--mode", "live", "--cache-dir", root / "cache-env", "--out", runs["env"]],
            {"OPENAI_BASE_URL": _url(server.base_url, user_b, pw_b)},
        )
        assert proc.returncode == 0, proc.stderr[-3000:]
        # the digits-only key as the bearer token
        runs["digits"] = root / "run-digits"
        proc = vp(["run", *common, "--base-url", server.base_url, "--mode", "live", "--cache-dir",
                   root / "cache-digits", "--out", runs["digits"]])  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-3000:]
        # a run that fails: its error line quotes the Basic credential, the key and a ?code= value
        server.inject("500", times=10_000, retry_after=0.01)
        failed = vp(["run", *common, "--base-url", _url(server.base_url, user_a, pw_a), "--mode", "live",
                     "--cache-dir", root / "cache-fail", "--out", root / "run-fail"])  # fmt: skip
        assert failed.returncode == 2 and "credentials seen" in failed.stderr, failed.stderr[-3000:]
        coded = vp(["run", *common, "--base-url", f"{server.base_url}?code={code}", "--mode", "live",
                    "--cache-dir", root / "cache-code", "--out", root / "run-code"])  # fmt: skip
        assert coded.returncode == 2 and "HTTP 404" in coded.stderr, coded.stderr[-3000:]  # the query broke the path
        seen = [r.headers.get("authorization", "") for r in server.chat_requests]
    # in this process: the first score embeds the captions (a subprocess would spend its CPU importing torch)
    first = cli_in_process(["score", runs["basic"]], env={"VLMPROPRIO_CACHE": env["VLMPROPRIO_CACHE"]})
    outputs.extend([first.stdout, first.stderr])
    assert first.returncode == 0, first.stderr[-3000:]
    for run in runs.values():
        done = [] if run == runs["basic"] else [vp(["score", run])]
        for proc in [*done, vp(["report", run])]:
            assert proc.returncode == 0, proc.stderr[-3000:]
    return {
        "root": root,
        "runs": runs,
        "fixtures": fixtures,
        "seen": seen,
        "outputs": outputs,
        "needles": [*_forms(user_a, pw_a), *_forms(user_b, pw_b), key, code, pw_a[2:18], pw_b[2:18]],
        "basic": [base64.b64encode(f"{u}:{p}".encode()).decode() for u, p in ((user_a, pw_a), (user_b, pw_b))],
        "key": key,
    }


def test_every_shape_was_really_sent_and_quoted(echoed):
    """Else this module would prove nothing: the server saw both Basic credentials and the digits-only key, and
    the transcripts hold its quotes, masked."""
    assert {f"Basic {b}" for b in echoed["basic"]} | {f"Bearer {echoed['key']}"} <= set(echoed["seen"])
    for run in echoed["runs"].values():
        texts = [p.read_text() for p in (run / "transcripts").rglob("*.json")]
        assert texts and all("credentials seen: Authorization: " in t for t in texts)
        assert any("credential ***" in t for t in texts)


def test_no_encoding_of_any_credential_reaches_a_file_or_the_console(echoed, figures):
    files = all_files(echoed["root"])
    names = {p.name for p in files}
    # every artefact the issue names: transcripts, audit.json, frames.csv, the report, the committed cassette
    assert {"audit.json", "frames.csv", "index.html", "openai_fake-vlm.jsonl", "cache.db"} <= names, names
    needles = [n.encode() for n in echoed["needles"]]
    leaks = [str(p) for p in files if any(n in p.read_bytes() for n in needles)]
    assert leaks == []
    console = "\n".join(echoed["outputs"])
    assert [n for n in echoed["needles"] if n in console] == []
    figures(
        "secrets: shapes (Basic URL credentials, digits-only key, query credentials)",
        files_searched=len(files),
        encodings_searched=len(needles),
        console_chars_searched=len(console),
        leaks=0,
    )


@pytest.mark.parametrize(
    "argv",
    [
        ["run", "--model", "reference", "--baseurl", "{url}"],  # a mistyped option: argparse prints its value
        ["run", "--model", "reference", "{url}"],
        ["run", "--model", "reference", "--mode", "{url}"],  # argparse: "invalid choice: 'http://...'"
    ],
)
def test_usage_errors_mask_the_url_credentials_they_print(argv, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    password, code = _password(), secrets.token_urlsafe(12)
    url = _url("http://vlm.example/v1", "carol", password) + f"?code={code}"
    proc = cli_in_process([a.format(url=url) for a in argv])
    assert proc.returncode == 2 and "error:" in proc.stderr, proc.stderr
    assert "***" in proc.stderr, proc.stderr  # the value was printed, masked
    for form in [*_forms("carol", password), code]:
        assert form not in proc.stderr + proc.stdout, proc.stderr
