"""Fault-injection campaigns: every fault kind x every workflow state x N seeds on the simulator,
each run judged from its session log and the simulator's truth (see docs/campaign.md)."""
