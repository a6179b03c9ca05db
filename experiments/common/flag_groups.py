"""The groups a command's flags are listed in, by the module that defines them: `--help` and the documentation's
flag tables both read this (it imports nothing, so the documentation build starts no JAX)."""
GROUPS = {"experiments.common.config_flags": "training settings",
          "experiments.common.training": "the run and its workdir",
          "experiments.common.environment_flags": "the environment"}
