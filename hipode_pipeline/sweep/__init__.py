"""`hipode sweep`: does HIPODE help a learner? Every arm on the same seeds and update budget.

plan     the arms, the budget, the artifacts (built through stage one when missing), the runs
worker   one run, in whatever process executes it (imports only the library)
engines  where runs execute: in this process, in local worker processes, or on Ray
report   statistics over seeds, the tables, quality.md / quality.json / quality.png
machine  the machine's CPU and load while the sweep runs
driver   the sweep end to end
"""
