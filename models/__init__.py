"""surftrack's bundled model, installed as the package data ``surftrack.models``
(``surftrack.paths.default_model_path``): ``default.pt`` and its ``MODEL_CARD.md``."""
