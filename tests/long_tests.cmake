# The release suite's long cases (over 20 s each on 2 cores, measured cold: scripts/test --all
# prints every stage's time, docs/testing.md the table). They carry the label `long`: the quick
# check (scripts/test, ctest --preset quick) leaves them out, the full run (scripts/test --all)
# runs them in ctest --preset release-long, so quick and release-long together are the whole
# release suite. Read by ctest after the suites' discovered cases (TEST_INCLUDE_FILES); the
# benchmarks' smoke runs and the browser test are labelled where they are added.
set(pulsetrack_long_tests
  TrackingSession.HoursLongTrackingKeepsIdsAndStaysDriftFree
  TrackingSession.DeformationFollowsTheTruthThroughAnInstrumentAndARedetection
  AnalyzeCli.CortexCaseBreathingAndCardiacAgainstTheTruth
  Robustness.HardCortexSceneKeepsFeaturesAndTheirIds
  Daemon.CaptureCycleCommandsAndGarbage
  Daemon.AStalledTrackStageStopsTheWatchdogAndHealthSaysFault
  StereoTracker.StereoRefreshTakesTheFirstPairsNoiseOut
  StereoTracker.StaticMatteCortexAt45cm
  StereoTracker.StaticGlossyCortexAt45cm
  VideoFiles.TrackReadsTwoFilesSideBySideAndTopBottomAndSeesADroppedFrame
  ValidateCli.StaticProtocolRegistrationTableIIStatisticsAndReport
  Keystores.BadSecurityFilesAreNamedAndTheDaemonDoesNotStart
  RealTexture.TrackedAgainstExactTruthAtEachResolution)
foreach(t IN LISTS pulsetrack_long_tests)
  set_tests_properties(${t} PROPERTIES LABELS long)
endforeach()
# The longest first, so that two run side by side to the end (a fresh clone has no cost data:
# in test order the soak, 168 s, started last and ran alone). Seconds, release, cold run.
set_tests_properties(TrackingSession.HoursLongTrackingKeepsIdsAndStaysDriftFree PROPERTIES COST 85)
set_tests_properties(AnalyzeCli.CortexCaseBreathingAndCardiacAgainstTheTruth PROPERTIES COST 63)
set_tests_properties(Robustness.HardCortexSceneKeepsFeaturesAndTheirIds PROPERTIES COST 48)
