"""What a fit returns and how it is judged: the Solution, the RESULTS verdicts."""
