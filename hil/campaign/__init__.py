"""Fault-injection campaigns: every fault kind x every workflow state x N seeds on the simulator,
each run judged from its session log and the simulator's truth; and the transport tier, faults
sent through the emulators to the real drivers in real time (see docs/campaign.md)."""
