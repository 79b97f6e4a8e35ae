"""agos.evaluator: the result side. The evaluator process that stores each episode record once
(SQLite), the paper's metrics as pure functions over records, paired statistics, failure
attribution, tables and reports, and their commands. Imports ``agos.runtime`` only.
"""
