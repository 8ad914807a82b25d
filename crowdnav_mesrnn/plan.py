"""Deprecated: moved to :mod:`crowdnav_mesrnn.studies.plan` and :mod:`crowdnav_mesrnn.studies.plan_budget`."""

from crowdnav_mesrnn._deprecated import warn_moved
from crowdnav_mesrnn.cli.predictor import (  # noqa: F401
    main_plan,
)
from crowdnav_mesrnn.studies.plan import (  # noqa: F401
    REPO_ROOT,
    STAGES,
    Candidate,
    Plan,
    Run,
    candidate_runs,
    execute,
    export,
    load_plan,
    parse_shard,
    read_done,
    run_dir,
    run_lock,
    seed_runs,
    selected_candidate,
    shard_filter,
    stage_runs,
    status,
    summary,
    train_run,
    yaml_scalar,
)
from crowdnav_mesrnn.studies.plan_budget import (  # noqa: F401
    Rate,
    dry_run,
    epoch_rates,
    measure_rate,
    observed_rates,
)

warn_moved(__name__, "crowdnav_mesrnn.studies.plan")
