"""Reading stored runs back as results: the paper's figures and tables, the reproduction report,
`esr ls`'s listing and the human calibration table.
"""
