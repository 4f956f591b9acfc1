"""Campaigns: many simulated runs over generated objects, judged from the simulation's truth."""
