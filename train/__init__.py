"""Training and evaluation of crater classifiers on the rendered manifest. Never imports bpy."""
