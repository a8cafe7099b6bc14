"""The program library: approved programs, their versions, analysis and run record."""
