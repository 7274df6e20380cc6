"""Target datasets in Minari format: recipes, reproducible builds, verification, downloads.

``ensure_dataset("offdyn/hopper-gravity-0p5/random-v0")`` installs a dataset if needed (from the
configured remote, else rebuilt from its recipe) and verifies it; ``load_installed(id)`` (or
``minari.load_dataset(id)``) reads it. Its ``env_spec`` is the task's source and its
``eval_env_spec`` the target. See the "Target datasets" section of the top-level README.
"""

from offdyn_bench.datasets.archive import ArchiveError
from offdyn_bench.datasets.build import BuildMismatchError, BuildResult, MissingPolicyError, build_dataset
from offdyn_bench.datasets.download import REMOTE_ENV, DownloadError, download_dataset, fetch_entry
from offdyn_bench.datasets.ensure import DatasetUnavailableError, ensure_dataset, load_installed
from offdyn_bench.datasets.install import InstallError, VerifyReport, datasets_root, is_installed, verify_installed
from offdyn_bench.datasets.manifest import MANIFEST_PATH, Entry, Manifest, ManifestError, read_manifest, write_manifest
from offdyn_bench.datasets.policies import MLPPolicy, Policy, PolicyError, UniformRandomPolicy, load_policy, save_policy
from offdyn_bench.datasets.recipes import (
    QUALITIES,
    Behaviour,
    Recipe,
    RecipeError,
    dataset_id,
    default_recipe,
    default_recipes,
    default_tasks,
    parse_dataset_id,
)
from offdyn_bench.datasets.transfer import TransferError, TransferLimits

__all__ = [
    "Recipe", "Behaviour", "QUALITIES", "dataset_id", "parse_dataset_id", "default_recipe", "default_recipes",
    "default_tasks",
    "Manifest", "Entry", "MANIFEST_PATH", "read_manifest", "write_manifest",
    "build_dataset", "BuildResult",
    "ensure_dataset", "load_installed", "download_dataset", "fetch_entry", "REMOTE_ENV", "TransferLimits",
    "datasets_root", "is_installed", "verify_installed", "VerifyReport",
    "Policy", "MLPPolicy", "UniformRandomPolicy", "load_policy", "save_policy",
    "RecipeError", "ManifestError", "MissingPolicyError", "BuildMismatchError", "DownloadError", "ArchiveError",
    "InstallError", "PolicyError", "TransferError", "DatasetUnavailableError",
]
