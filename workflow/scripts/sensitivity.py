from pathlib import Path

from surffin.sensitivity import OUTPUTS, run_sensitivity

# run_sensitivity names its files itself (OUTPUTS): the rule's outputs must be those files.
outputs = {key: Path(path) for key, path in snakemake.output.items()}
out_dir = outputs["store"].parent
if outputs != {key: out_dir / name for key, name in OUTPUTS.items()}:
    raise ValueError(f"rule sensitivity: outputs {outputs} differ from surffin.sensitivity.OUTPUTS in {out_dir}")
run_sensitivity(out_dir, draws=snakemake.params.draws, seed=snakemake.params.seed, log_path=snakemake.log[0])
