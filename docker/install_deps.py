"""Install the service's dependencies from pyproject.toml (the base image provides torch)."""

import subprocess
import sys
import tomllib

meta = tomllib.load(open(sys.argv[1], "rb"))["project"]
deps = meta["dependencies"] + [d for d in meta["optional-dependencies"]["service"] if not d.startswith("torch")]
subprocess.check_call([sys.executable, "-m", "pip", "install", *deps])
