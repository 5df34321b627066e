"""The paper's ablation studies as reproducible sweeps (`make ablate`).

`experiments.studies` defines the studies and presets as frozen `ExperimentConfig`s
derived from a base config; `experiments.planning` turns the pending runs into jobs (one
per row) and packs them into worker processes; `experiments.runner` executes them
(skipping finished runs, resuming interrupted ones; a row's seeds train together, see
`experiments.multiseed`) and scores them (`experiments.evaluation`). `experiments.stats`
computes the tables' numbers (mean ± std over seeds, bootstrap intervals, verdicts), and
`experiments.aggregate` writes the tables, CSVs, READMEs and, through
`experiments.plots`, the figures under `experiments/results/<preset>/`. Command line:
`python -m experiments --help`.
"""
