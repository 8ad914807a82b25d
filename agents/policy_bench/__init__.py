"""``crowdnav-mesrnn bench-policy IMPORT_PATH``: your own policy on the held-out scenes, on one page.

The policy (:mod:`agents.policy_bench.policy`: an object with SB3's ``predict``, a callable ``obs -> action``, or a
factory of one, named by ``package.module:attr``) crosses the fixed episode lists of the held-out scenes with each
forecast arm it asks for; the sampling and search planners and the privileged ceiling are read on the same episodes
(:mod:`agents.policy_bench.references`: from the committed planner grid when it holds exactly those episodes, else
run here); exact McNemar tests on success, Holm-corrected, with the interval that matches them and a verdict
(:mod:`agents.policy_bench.run`); ``report.md``, ``report.json`` and ``success_by_scene.png``
(:mod:`agents.policy_bench.report`). The command line (:mod:`agents.policy_bench.cli`) checks every argument before
anything heavy is imported. The guide: ``docs/policies.md``; a complete example package: ``examples/my_policy``.
"""

from __future__ import annotations

from agents.policy_bench.cli import add_parser, main

__all__ = ["add_parser", "main"]
