"""The paper's ablation studies as reproducible sweeps (`make ablate`).

`experiments.studies` defines the studies and presets as frozen `ExperimentConfig`s
derived from a base config, `experiments.runner` trains and evaluates them (skipping
finished runs, resuming interrupted ones; a row's seeds train together, see
`experiments.multiseed`), and `experiments.aggregate` writes the tables (mean ± std over
seeds), bootstrap intervals and verdicts, CSVs, plots and READMEs under
`experiments/results/<preset>/`. Command line:
`python -m experiments --help`.
"""
