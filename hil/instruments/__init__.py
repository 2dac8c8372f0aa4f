"""What hil expects of a robot and a tracker: the Protocols, their state records and typed errors."""
