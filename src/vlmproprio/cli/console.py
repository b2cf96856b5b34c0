"""What the command prints: secrets masked in every stream and log record, progress bars over a command's stages."""

from __future__ import annotations


class ScrubbingStream:
    """A console stream that masks secrets (vlmproprio.secrets) in everything written to it."""

    def __init__(self, stream) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        from vlmproprio.secrets import scrub

        self._stream.write(scrub(text) if isinstance(text, str) else text)
        return len(text)

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def scrub_log_records() -> None:
    """Mask secrets in every log record (libraries' debug logs included) before any handler sees it."""
    import logging

    from vlmproprio.secrets import scrub

    factory = logging.getLogRecordFactory()
    if getattr(factory, "vlmproprio_scrubs", False):
        return

    def make(*args, **kwargs):
        record = factory(*args, **kwargs)
        try:
            message = record.getMessage()
        except Exception:  # a malformed log call: leave it to logging's own error handling
            return record
        clean = scrub(message)
        if clean != message:
            record.msg, record.args = clean, None
        return record

    make.vlmproprio_scrubs = True  # type: ignore[attr-defined]
    logging.setLogRecordFactory(make)


def stages(desc: str, total: int, enabled: bool):
    """A progress bar over a command's stages (tqdm, on stderr; off with --no-progress or when not a terminal)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="step", disable=not enabled or None, leave=False)
