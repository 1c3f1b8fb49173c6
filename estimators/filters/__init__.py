"""The recursive filters (`ekf`, `ukf`, `ukf-bias`): each filter beside the state they share
(`kalman_base`, `filter_params`) and its compiled twin (`_compiled_ekf`, `_compiled_ukf`, `_compiled`)."""
