# Makes `import mcdenoise_train` work when pytest runs from training/.
