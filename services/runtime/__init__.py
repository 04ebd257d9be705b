"""What every service process shares: the service base, the Zenoh session, the deadline loop,
the supervisor, sd_notify, config loading, the clock and the router."""
