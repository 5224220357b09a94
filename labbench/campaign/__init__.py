"""Campaigns: a sweep spec's points run one after another on one device (docs/campaign.md).

``plan`` (the points as runs, checked before anything moves), ``engine`` (running them,
resumably), ``rows`` (one row each, with the exact sampled theory's prediction),
``passivity`` (the passive bounds a Z-width is read against), ``settings`` (the rig's
``[campaign]`` table), ``report`` (the campaign's report).
"""
