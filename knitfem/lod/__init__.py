"""The mechanical level of detail: the bounding volume and Γ, the reduced
model (M^V = Γᵀ M Γ by PtAP, Q^V = Γᵀ Q), its sampled forces, the shell
stretch, the mixed full/reduced model and its adaptation."""
