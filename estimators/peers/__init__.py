"""The community's estimators behind our interface: VQF and Fusion (`vqf_fusion`), the `ahrs`
package's filters (`ahrs_filters`) and their compiled twins (`_compiled_ahrs`)."""
