"""The procedure controller: state machine, registration, planning, gate, compensation, lock."""
