"""vlmproprio: does proprioception make a VLM's captions and subtask segmentations of robot episodes better?"""

__version__ = "0.1.0"
