"""The model's mathematics, no mesh: signaling, protocols, material and growth laws, heterogeneity, the surrogate."""
