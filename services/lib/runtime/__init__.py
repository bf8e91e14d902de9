"""Runtime shared by every service: Zenoh profiles, clocks, lockstep gate, service base."""
