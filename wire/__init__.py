"""The bodies of the data messages federates exchange: one typed struct per message kind."""
