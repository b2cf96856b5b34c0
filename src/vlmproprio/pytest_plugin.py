"""pytest plugin (registered through the ``pytest11`` entry point): options and fixtures for benchmark/.

Kept import-light: pytest loads it in every session, including ones that never touch a model.
"""
