"""One Unity instance: its build, its leased port, its process (launched under a guard), the
communicator to it and the policy that restarts it."""
