"""Your own estimators in the table: a module or file of yours (`user`), a FilterPy filter
(`filterpy`), a trajectory another program wrote (`trajectory_file`)."""
