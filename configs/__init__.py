"""surftrack's bundled configuration files, installed as the package data ``surftrack.configs``
(``surftrack.paths.configs_dir``): ``instruments/``, ``synth/``, ``track/``, ``train/``, ``schemas/``."""
