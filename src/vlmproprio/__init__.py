"""vlmproprio: does proprioception make a VLM's captions and subtask segmentations of robot episodes better?

From Python: ``vlmproprio.evaluate(model=..., episodes=..., conditions=..., out=...)`` (vlmproprio.api), imported
on first use so that ``import vlmproprio`` stays light.
"""

__version__ = "0.1.0"
__all__ = ["evaluate"]


def __getattr__(name: str):
    if name == "evaluate":
        from vlmproprio.api import evaluate

        return evaluate
    raise AttributeError(f"module 'vlmproprio' has no attribute {name!r}")
