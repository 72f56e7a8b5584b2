"""``esa-compare``: does ESA help on my task? A placebo-controlled verdict in one command.

Trains the baseline, ESA and its controls on the same seeds, evaluates each run at fixed
steps, and judges ESA against the baseline and the placebo with the statistics of the
project's own studies (which run and judge through this package): IQM learning curves with
95 % bootstrap CIs, ``P(arm better)`` with its CI and a Holm-corrected Mann-Whitney test.
Needs the ``compare`` extra: ``pip install "esa-client[compare]"``.

Run ``esa-compare --help`` (or ``python -m esa_client.compare --help``).
"""
